"""Webhook and e-mail notifications (the notify section of daemon.yaml)."""
