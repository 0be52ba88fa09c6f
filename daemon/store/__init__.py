"""The journal (store in daemon.yaml): SQLite, the PostgreSQL fleet store and its outbox."""
