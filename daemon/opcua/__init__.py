"""OPC UA results server (issue 25): OPC 40001-1 identification, state, OPC 40001-101 results."""
