"""Probing programs: tool path, geometry, safety check, cycle time, dialects."""
