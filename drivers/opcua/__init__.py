"""OPC UA: link and configuration schema (address space in contracts)."""
