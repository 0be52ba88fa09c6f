"""rumba-cnc simulators package."""
