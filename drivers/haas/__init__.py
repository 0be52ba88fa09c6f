"""Haas NGC over its Ethernet data port (Machine Data Collection: ?Q600 / ?E macro variables)."""
