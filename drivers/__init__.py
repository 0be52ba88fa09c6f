"""rumba-cnc drivers package."""
