"""The fleet page: a read-only web service over the PostgreSQL fleet store."""
