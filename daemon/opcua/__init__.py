"""OPC UA results server: OPC 40001-1 identification, state, OPC 40001-101 results."""
