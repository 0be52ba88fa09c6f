"""End-to-end demonstrations: the embedded simulator, LinuxCNC."""
