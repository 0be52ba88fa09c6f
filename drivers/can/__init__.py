"""CAN operator panel: panel and configuration schema (frames in contracts)."""
