"""rumba-cnc daemon package."""
