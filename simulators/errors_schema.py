"""Errors YAML of the simulated machine: the "truth" it carries (validated, unknown keys fail).

Units in the file: link rotations (EA0B, EB0Z …) in µrad, link translations (EX0C …) in µm,
setup errors in µm, noise in µm, positions of obstacles in mm. Effect parameters are given in the
units the effect model declares (``identification.effects``); the loader converts to mm / rad.
``rotary_error_motion`` is in the axis' fixed frame, ISO 230-7 (options ``orders``,
``components``; config/errors/README.md), as the gap diagnosis reports it. A linear axis'
``cyclic_error`` (a pitch error) and ``local_bump`` are effects too, outside the diagnosis'
library (``identification.axis_local_effects``; positions in controller mm).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Annotated, Any

from pydantic import Field, field_validator

from contracts.yaml_files import ConfigError, StrictModel, read_yaml, validate_file

Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]
ISO_LINK = re.compile(r"\AE[XYZABC]0[XYZABC]\Z")  # fullmatch: "$" lets a final "\n" by




class SetupFile(StrictModel):
    """Setup errors: where each ball and the stylus tip really are, relative to nominal."""

    balls_um: dict[str, Vec3] = {}  # ball id → offset in the last workpiece frame
    probe_um: Vec3 = [0.0, 0.0, 0.0]  # stylus-tip offset in the last tool frame
    random_balls_std_um: float = Field(0.0, ge=0, le=5000)  # drawn by seed, added to balls_um
    random_probe_std_um: float = Field(0.0, ge=0, le=5000)


class ProbeFile(StrictModel):
    """The probing system: true stylus size, pre-travel and repeatability."""

    stylus_diameter_mm: float = Field(6.0, gt=0, le=50)
    pretravel_um: float = Field(0.0, ge=0, le=200)  # along the move, after contact
    touch_noise_um: float = Field(0.0, ge=0, le=100)  # per touch, along the approach
    # The controller samples the probe input this often (LinuxCNC: the servo period): the latch
    # lies past the contact by feed x period x U(0, 1), a scatter that grows with the feed.
    sample_period_ms: float = Field(0.0, ge=0, le=100)
    # Per visit of a ball (the five touches share it): the centre repeatability (thesis §3.4).
    centre_noise_um: Vec3 = [0.0, 0.0, 0.0]

    @field_validator("centre_noise_um")
    @classmethod
    def _nonneg(cls, v: list[float]) -> list[float]:
        if any(x < 0 for x in v):
            raise ValueError("noise standard deviations must be >= 0")
        return v


class ObstacleFile(StrictModel):
    """A sphere in the last workpiece frame the stylus can hit early (a chip, a clamp edge)."""

    name: str
    centre_mm: Vec3
    radius_mm: float = Field(gt=0, le=500)


class IndexingFile(StrictModel):
    """Non-repeatable positioning of the rotary axes (issue 21): every indexation stops at the
    command + δ, δ ~ N(0, σ) drawn per indexation and axis (µrad 1σ by axis letter)."""

    repeatability_urad: dict[str, Annotated[float, Field(ge=0, le=1000)]] = {}


class BallStepFile(StrictModel):
    """A ball knocked during the run (issue 21): from ``t_s`` (machine time, s) on it sits
    ``vector_um`` away (last workpiece frame)."""

    ball: str
    t_s: float = Field(ge=0)
    vector_um: Vec3


class EffectFile(StrictModel):
    """One effect family instance, e.g. ``{family: straightness, axis: X, params: {...}}``."""

    family: str
    axis: str | None = None
    params: dict[str, float] = {}
    options: dict[str, Any] = {}


class AxisWarmupFile(StrictModel):
    """Warm-up of one controller axis (simulators/thermal.py): TCP drift when fully warm (µm),
    time constant (s), rise of the structure temperature a sensor on it reads (°C)."""

    amplitude_um: float = Field(ge=-500, le=500)
    tau_s: float = Field(gt=0, le=86400)
    rise_c: float = Field(0.0, ge=-50, le=50)


class ThermalFile(StrictModel):
    """The machine's thermal state during the run (issue 22): per axis X Y Z a first-order
    warm-up from ``start_state`` (0 cold, 1 warm) when the simulated machine starts (its first
    program; later programs on the same controller find it warmer)."""

    axes: dict[str, AxisWarmupFile] = {}
    start_state: float = Field(0.0, ge=0, le=1)
    ambient_c: float = Field(20.0, ge=-20, le=60)

    @field_validator("axes")
    @classmethod
    def _xyz(cls, v: dict[str, AxisWarmupFile]) -> dict[str, AxisWarmupFile]:
        bad = sorted(set(v) - set("XYZ"))
        if bad:
            raise ValueError(f"axes {bad}: the warm-up moves the TCP along X, Y or Z")
        return v


class ErrorsFile(StrictModel):
    machine: str | None = None  # name of the machine file these errors belong to (checked)
    seed: int = Field(0, ge=0, lt=2**63)  # default random seed (``--seed`` overrides)
    links: dict[str, float] = {}  # ISO 230-1 name → µrad (rotations) or µm (translations)
    setup: SetupFile = SetupFile()
    probe: ProbeFile = ProbeFile()
    absent_balls: list[str] = []  # balls not on the table: their touches do not trigger
    obstacles: list[ObstacleFile] = []
    indexing: IndexingFile = IndexingFile()  # per-indexation scatter of the rotary axes
    ball_steps: list[BallStepFile] = []  # balls knocked during the run
    effects: list[EffectFile] = []
    thermal: ThermalFile | None = None  # warm-up during the run (simulators/thermal.py)

    @field_validator("links")
    @classmethod
    def _iso(cls, v: dict[str, float]) -> dict[str, float]:
        for name in v:
            if not isinstance(name, str) or not ISO_LINK.fullmatch(name):
                raise ValueError(f"{name!r} is not an ISO 230-1 location error name (e.g. EB0Z)")
        return v


def link_to_model(name: str, value: float) -> float:
    """µm → mm for translations (EX0C), µrad → rad for rotations (EB0C)."""
    return value * 1e-3 if name[1] in "XYZ" else value * 1e-6


def errors_from_dict(data: Any, path: Path | str = "<errors>") -> ErrorsFile:
    if data is None:
        data = {}
    return validate_file(ErrorsFile, path, data)


def load_errors(path: Path | str) -> ErrorsFile:
    """Load and validate an errors file; ``ConfigError`` names file, key and reason."""
    return errors_from_dict(read_yaml(Path(path)), path)


__all__ = ["ConfigError", "ErrorsFile", "errors_from_dict", "link_to_model", "load_errors"]
