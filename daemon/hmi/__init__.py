"""The operator web page (hmi in daemon.yaml) and what the fleet page shares: access, auth, TLS."""
