"""Argument values the parsers and the commands share, kept light (no numpy)."""

from __future__ import annotations

DEFAULT_STYLUS_DIAMETER_MM = 6.0
"""The shipped plans' stylus: the radius health figure of `rumba analyze` and `rumba gap`."""

# copies of constants whose modules import numpy, pydantic or dataclasses (tests/test_cli_fast.py
# holds them equal): the parser of `rumba --help` must not import those
CENTRES_FORMATS = ("auto", "csv", "kinopt", "dmis")
"""``contracts.importers.FORMATS``: the --centres file formats."""
CENTRES_FRAMES = ("machine", "instrument")
"""``contracts.centres_file.FRAMES``: the frames of a centres file."""
GAP_SPLITS = ("auto", "pose", "time")
"""``identification.gap.split.SPLITS``: the held-out splits of `rumba gap`."""
GAP_FAMILIES = ("thermal_drift", "linear_scale", "straightness", "angular_motion",
                "rotary_positioning", "rotary_error_motion", "gravity_sag", "probe_pretravel",
                "artefact_instability")
"""``identification.effects.FAMILIES``: the effect families of `rumba gap --families`."""
DIALECT_NAMES = ("fanuc", "haas", "siemens", "heidenhain", "linuxcnc")
"""``tuple(contracts.dialects.DIALECTS)``: every controller dialect record, in its order."""
GCODE_DIALECTS = ("fanuc", "heidenhain", "linuxcnc", "siemens")
"""The sorted template families of the dialect records (``contracts.dialects``): `rumba gcode`
lists them, then haas (the fanuc family's variant)."""
