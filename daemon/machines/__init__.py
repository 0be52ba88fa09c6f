"""The machines section of daemon.yaml: each machine's files, link, triggers, tolerances."""
