"""The daemon process: a session per machine, triggers, HMI server, fleet link, systemd."""
