"""Modbus TCP: link and configuration schema (register map in contracts)."""
