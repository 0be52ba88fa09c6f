"""The target file of ``rumba plan``: link uncertainties to reach, the plan to compare with, the
candidate poses (strict schema: unknown keys are errors, one line naming file and key).

Example: config/plans/targets/shift_start.yaml. Link names are ISO 230-1 location errors
(METHOD.md §2); a target is a standard uncertainty in µrad (rotations) or µm (translations), or
``reference``: what the reference plan itself is predicted to reach.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Annotated, Any

from pydantic import Field, field_validator, model_validator

from contracts.setup_files import SAFE_NAME, Range2
from contracts.yaml_files import ConfigError, StrictModel, read_yaml, validate_file

LINK_NAME = re.compile(r"\AE[XYZABC]0[XYZABC]\Z")
Uncertainty = Annotated[float, Field(gt=0, le=1e4)]


class CandidateGrid(StrictModel):
    """The B/C grid the optimiser chooses from (then filtered by the safety check)."""

    b_step_deg: float = Field(15.0, ge=1, le=90)
    c_step_deg: float = Field(15.0, ge=1, le=90)
    b_range_deg: Range2 | None = None  # default: the machine's travel of the first rotary axis

    @field_validator("b_range_deg")
    @classmethod
    def _ordered(cls, v: list[float] | None) -> list[float] | None:
        if v is not None and v[0] > v[1]:
            raise ValueError(f"minimum {v[0]:g} must not be above maximum {v[1]:g}")
        return v


class TargetsFile(StrictModel):
    name: str  # of the plan written
    reference_plan: str  # a plan file, relative to this file: compared with, probing kept
    links: dict[str, Any] = Field(min_length=1)  # µrad / µm > 0, or "reference"
    # centre repeatability per controller axis (thesis §3.4), the σ of the prediction
    repeatability_um: Annotated[list[Uncertainty], Field(min_length=3, max_length=3)] = \
        [0.66, 0.98, 0.44]
    validate_poses: int = Field(0, ge=0, le=50)  # extra held-out poses for prediction
    two_speed: bool = True  # write feeds.fast_probe_mm_min (used where the dialect can)
    clearance_mm: float | None = Field(None, gt=0, le=500)  # None: the reference plan's
    candidates: CandidateGrid = CandidateGrid()

    @field_validator("name")
    @classmethod
    def _safe(cls, v: str) -> str:
        if not SAFE_NAME.fullmatch(v):
            raise ValueError("must be 1-32 characters of letters, digits, '_', '.', '-' "
                             "(it is written into G-code)")
        return v

    @field_validator("links")
    @classmethod
    def _links(cls, v: dict) -> dict:
        out: dict[str, float | str] = {}
        for k, u in v.items():
            if not LINK_NAME.fullmatch(str(k)):
                raise ValueError(f"{k!r} is not an ISO 230-1 location error name "
                                 "(E<error><0><axis>, e.g. EB0Z, EX0C)")
            ok = u == "reference" or (isinstance(u, int | float) and not isinstance(u, bool)
                                      and math.isfinite(u) and 0 < u <= 1e4)
            if not ok:
                raise ValueError(f"{k}: {u!r}: expected a standard uncertainty in (0, 1e4] "
                                 "(µrad, µm for a translation) or 'reference'")
            out[str(k)] = u if u == "reference" else float(u)
        return out

    @model_validator(mode="after")
    def _plan_path(self) -> TargetsFile:
        if not self.reference_plan.strip() or "\x00" in self.reference_plan:
            raise ValueError("reference_plan: expected the path of a plan file")
        return self


def load_targets_file(path: Path | str) -> TargetsFile:
    """Read and validate a target file (``ConfigError`` naming file and key)."""
    return validate_file(TargetsFile, path, read_yaml(path))


def reference_path(targets: TargetsFile, path: Path | str) -> Path:
    """The reference plan's path: relative paths are relative to the target file."""
    p = Path(targets.reference_plan)
    p = p if p.is_absolute() else Path(path).parent / p
    if not p.is_file():
        raise ConfigError(f"{path}: reference_plan: {p} is not a file")
    return p
