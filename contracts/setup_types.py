"""Shared pieces of the setup-file schemas: safe names, ceilings and bounded numbers."""

from __future__ import annotations

import math
import re
from typing import Annotated

from pydantic import AfterValidator, Field

from contracts.result_lines import MAX_RESULT_MM

SAFE_NAME = re.compile(r"\A(?!\.+\Z)[A-Za-z0-9_.-]{1,32}\Z")  # not ".", ".."
"""Names that reach G-code (ball ids, machine and plan names) must match this: no spaces,
parentheses, semicolons, quotes or line breaks, so nothing can be injected into a program.
Use ``fullmatch``: with ``match`` and ``$`` a trailing newline would slip through (``\\Z`` also
guards a caller that uses ``match``)."""

MAX_POSES = 2_000
"""Ceiling on the poses of a plan (list or grid; the biggest shipped plan has 175), checked
before a grid is expanded."""
MAX_TOUCHES = 20_000
"""Ceiling on the touches of one program: visits (poses × repeats, + 1 with drift_check) ×
balls × 5 (the biggest shipped plan gives 3 500)."""
MAX_BALLS = 32
"""Ceiling on the balls of an artefact (the shipped ones have 4 or 5)."""


# Every length and angle of a setup file is bounded like a latched value (±1e5 mm or °): a finite
# but absurd number (1e308) would otherwise reach the kinematics and fail deep inside as a
# singular matrix instead of naming the key.
Bounded = Annotated[float, Field(ge=-MAX_RESULT_MM, le=MAX_RESULT_MM)]
# Free text kept for the audit trail (a serial number, a certificate): one printable line.
Record = Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[^\x00-\x1f\x7f]+$")]
Vec3 = Annotated[list[Bounded], Field(min_length=3, max_length=3)]
Range2 = Annotated[list[Bounded], Field(min_length=2, max_length=2)]

MIN_DIRECTION_NORM = 1e-9
"""A direction shorter than this cannot be normalised meaningfully (its direction would be
rounding noise); the schemas' vectors are written as unit vectors such as [0, 0, 1]."""


def _direction(v: list[float]) -> list[float]:
    """A direction vector must be normalisable: finite (``Bounded``) and not zero — a zero
    spindle axis or axis direction would turn into NaN in every transform further on."""
    if not math.sqrt(sum(x * x for x in v)) >= MIN_DIRECTION_NORM:
        raise ValueError(f"must be a non-zero direction such as [0, 0, 1], got "
                         f"{[float(x) for x in v]} (length below {MIN_DIRECTION_NORM:g})")
    return v


Direction = Annotated[Vec3, AfterValidator(_direction)]


def safe_name(v: str) -> str:
    if not SAFE_NAME.fullmatch(v):
        raise ValueError(
            "must be 1-32 characters of letters, digits, '_', '.', '-' (it is written into G-code)"
        )
    return v
