"""The volumetric map of the linear axes: their 18 ISO 230-1 motion errors as smooth functions,
estimated with the links and setups from the same probe and balls (METHOD.md §7)."""
