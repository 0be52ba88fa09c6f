"""LinuxCNC: linuxcncrsh and local links, program rewriting, schema."""
