"""Errors YAML of the simulated machine: the "truth" it carries (validated, unknown keys fail).

Units in the file: link rotations (EA0B, EB0Z …) in µrad, link translations (EX0C …) in µm,
setup errors in µm, noise in µm, positions of obstacles in mm. Effect parameters are given in the
units the effect model declares (``identification.effects``); the loader converts to mm / rad.
``rotary_error_motion`` is in the axis' fixed frame, ISO 230-7 (options ``orders``,
``components``; config/errors/README.md), as the gap diagnosis reports it. A linear axis'
``cyclic_error`` (a pitch error) and ``local_bump`` are effects too, outside the diagnosis'
library (``identification.axis_local_effects``; positions in controller mm).
``motion_errors``: the 18 motion errors of the linear axes as Legendre series over an interval
of each axis, or drawn at random (``simulators.motion_truth``).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Annotated, Any

from pydantic import ConfigDict, Field, ValidationError, field_validator, model_validator

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
    """Non-repeatable positioning of the rotary axes: every indexation stops at the
    command + δ, δ ~ N(0, σ) drawn per indexation and axis (µrad 1σ by axis letter)."""

    repeatability_urad: dict[str, Annotated[float, Field(ge=0, le=1000)]] = {}


class BallStepFile(StrictModel):
    """A ball knocked during the run: from ``t_s`` (machine time, s) on it sits
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
    """The machine's thermal state during the run: per axis X Y Z a first-order
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


Range = Annotated[list[float], Field(min_length=2, max_length=2)]


def _ordered(v: list[float] | None, what: str, strict: bool) -> list[float] | None:
    if v is not None and (v[0] > v[1] or (strict and v[0] == v[1])):
        raise ValueError(f"{what}: expected [low, high] with low {'<' if strict else '<='} "
                         f"high, got {v}")
    return v


class MotionFunctionFile(StrictModel):
    """One motion error: Legendre coefficients of P0, P1, … over the axis' interval, µm for a
    translation (EXX, EYX …), µrad for a rotation (EAX …)."""

    legendre: list[Annotated[float, Field(ge=-1e5, le=1e5)]] = Field(min_length=1,
                                                                     max_length=16)


class MotionAxisFile(StrictModel):
    """The motion errors of one linear axis: ``range_mm`` (controller mm, default its travel)
    is the interval u ∈ [−1, 1] spans, then one entry per error of this axis (EXX … ECX for X;
    checked by ``MotionErrorsFile``, which knows the letter)."""

    model_config = ConfigDict(extra="allow", frozen=True, allow_inf_nan=False)
    range_mm: Range | None = None

    @field_validator("range_mm")
    @classmethod
    def _range(cls, v: list[float] | None) -> list[float] | None:
        return _ordered(v, "range_mm", strict=True)

    def functions(self) -> dict[str, MotionFunctionFile]:
        """The errors given (validated by ``MotionErrorsFile``)."""
        return {k: MotionFunctionFile.model_validate(v)
                for k, v in (self.model_extra or {}).items()}


class RandomSmoothFile(StrictModel):
    """A random smooth machine: every motion error of ``axes`` drawn from ``seed``, its max |e|
    over the interval uniform in ``translation_um`` / ``rotation_urad`` (a number or [low,
    high]), Legendre degrees 1..``order`` with a spectrum falling as 1/k
    (``identification.linmap.basis.random_smooth``)."""

    seed: int = Field(0, ge=0, lt=2**63)
    translation_um: Annotated[float, Field(ge=0, le=1000)] | Range = 10.0
    rotation_urad: Annotated[float, Field(ge=0, le=5000)] | Range = 20.0
    order: int = Field(4, ge=1, le=12)
    axes: list[str] = ["X", "Y", "Z"]
    # the interval of each axis the amplitude holds over (controller mm; default its travel)
    range_mm: dict[str, Range] = {}

    @field_validator("translation_um", "rotation_urad")
    @classmethod
    def _amp(cls, v: float | list[float]) -> float | list[float]:
        if isinstance(v, list):
            if not all(0 <= x <= 5000 for x in v):
                raise ValueError(f"amplitudes must be within 0..5000, got {v}")
            _ordered(v, "amplitude", strict=False)
        return v

    @field_validator("axes")
    @classmethod
    def _axes(cls, v: list[str]) -> list[str]:
        bad = [a for a in v if a not in ("X", "Y", "Z")]
        if bad or len(set(v)) != len(v):
            raise ValueError(f"expected distinct letters among X, Y, Z, got {v}")
        return v

    @field_validator("range_mm")
    @classmethod
    def _ranges(cls, v: dict[str, list[float]]) -> dict[str, list[float]]:
        for k, r in v.items():
            if k not in ("X", "Y", "Z"):
                raise ValueError(f"{k!r}: expected a linear axis letter X, Y or Z")
            _ordered(r, k, strict=True)
        return v

    def amplitude(self, rotation: bool) -> tuple[float, float]:
        v = self.rotation_urad if rotation else self.translation_um
        return (float(v[0]), float(v[1])) if isinstance(v, list) else (float(v), float(v))


class MotionErrorsFile(StrictModel):
    """The 18 motion errors of the linear axes (ISO 230-1), applied just after each axis'
    motion in the truth's chain (``kinematics.ChainState.motion_errors``): per axis X, Y, Z
    Legendre series, plus an optional random smooth draw (the two add up)."""

    X: MotionAxisFile | None = None
    Y: MotionAxisFile | None = None
    Z: MotionAxisFile | None = None
    random_smooth: RandomSmoothFile | None = None

    @model_validator(mode="after")
    def _names(self) -> MotionErrorsFile:
        for letter in "XYZ":
            ax = getattr(self, letter)
            if ax is None:
                continue
            allowed = [f"E{c}{letter}" for c in "XYZABC"]
            for key, value in (ax.model_extra or {}).items():
                if key not in allowed:
                    raise ValueError(f"{letter}.{key}: unknown key; axis {letter} has "
                                     f"range_mm and the motion errors {', '.join(allowed)}")
                try:
                    MotionFunctionFile.model_validate(value)
                except ValidationError as e:
                    first = e.errors()[0]
                    loc = ".".join(str(x) for x in first["loc"])
                    msg = ("unknown key (expected legendre)" if first["type"] == "extra_forbidden"
                           else first["msg"])
                    raise ValueError(f"{letter}.{key}{'.' + loc if loc else ''}: "
                                     f"{msg}") from None
        return self


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
    # the 18 motion errors of the linear axes (simulators/motion_truth.py)
    motion_errors: MotionErrorsFile | None = None

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
