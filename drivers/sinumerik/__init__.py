"""SINUMERIK OPC UA profile: the control's own OPC UA server (file system, Select, R parameters)."""
