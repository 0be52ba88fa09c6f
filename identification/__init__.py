"""The RUMBA identification core: kinematics, estimation, analyses (numpy/scipy only, no I/O)."""
