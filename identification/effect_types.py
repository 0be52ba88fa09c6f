"""What one effect is: the ``Effect`` of a family on one axis, where it acts and its context.

Every effect is one *family instance* (e.g. straightness of the X axis) with a small parameter
vector given in report units (µm, µrad, µm/h …, listed in ``units``). An effect acts in at most
three places, mirroring where it physically enters the measurement (METHOD.md §6):

* ``motion_errors`` — component errors of machine axes, applied just *after* the axis motion
  (ISO 230-1 notation, seed 003 §5.2: EXX, EYX … ; kinematics.ChainState.motion_errors), model
  units mm / rad as functions of the model joint value q (mm or rad);
* ``ball_offset_mm`` — a displacement of the ball centre in the last workpiece frame (the frame
  of the ball setup errors): rod sag under gravity, a creeping ball;
* ``touch_offset_mm`` — an additive offset of the latched controller X, Y, Z of each touch:
  thermal drift of the reading, probe pre-travel.

The families themselves are in ``axis_effects`` (motion errors) and ``offset_effects`` (ball and
touch offsets); ``effects`` is their registry.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np

from identification.kinematics import Machine, MotionErrorFn

UM = 1e-3  # µm → mm
URAD = 1e-6  # µrad → rad
XYZ = "XYZ"
ABC = "ABC"


@dataclass(frozen=True)
class EffectContext:
    """Where and when every touch (or ball centre) was taken; all arrays have N rows.

    ``xyz_mm`` are controller coordinates, ``ball_nominal_mm`` ball centres in the last workpiece
    frame (nominal + setup), ``direction`` the nominal approach direction of the tool relative to
    the workpiece in the machine frame (probing-log ``dir_*``), ``touch`` 1-4 equator diagonals,
    5 pole (0 for a ball centre rather than a touch).
    """

    t_s: np.ndarray
    b_deg: np.ndarray
    c_deg: np.ndarray
    ball: np.ndarray
    touch: np.ndarray
    direction: np.ndarray
    xyz_mm: np.ndarray
    ball_nominal_mm: np.ndarray
    rod_length_mm: np.ndarray

    def __len__(self) -> int:
        return int(np.asarray(self.t_s).shape[0])


@dataclass(frozen=True)
class Effect:
    """One family instance. ``params`` are always in ``units`` (report units), never mm/rad."""

    family: str
    axis: str | None
    param_names: tuple[str, ...]
    units: tuple[str, ...]
    _motion: Callable[[np.ndarray], dict[str, MotionErrorFn]] | None = field(
        default=None, repr=False, compare=False)
    _ball: Callable[[np.ndarray, EffectContext], np.ndarray] | None = field(
        default=None, repr=False, compare=False)
    _touch: Callable[[np.ndarray, EffectContext], np.ndarray] | None = field(
        default=None, repr=False, compare=False)
    linear: bool = True  # contribution linear in params (lets the diagnosis linearise exactly)
    note: str = ""

    @property
    def n_params(self) -> int:
        return len(self.param_names)

    @property
    def label(self) -> str:
        return self.family if self.axis is None else f"{self.family}:{self.axis}"

    def _check(self, params: np.ndarray) -> np.ndarray:
        p = np.asarray(params, float).reshape(-1)
        if p.shape[0] != self.n_params:
            raise ValueError(f"{self.label}: expected {self.n_params} parameters "
                             f"{self.param_names}, got {p.shape[0]}")
        return p

    def motion_errors(self, params: np.ndarray) -> dict[str, MotionErrorFn]:
        """Component-error functions per axis letter (model units mm / rad)."""
        p = self._check(params)
        return {} if self._motion is None else self._motion(p)

    def ball_offset_mm(self, params: np.ndarray, ctx: EffectContext) -> np.ndarray:
        """(N, 3) ball-centre displacement in the last workpiece frame, mm."""
        p = self._check(params)
        if self._ball is None:
            return np.zeros((len(ctx), 3))
        return self._ball(p, ctx)

    def touch_offset_mm(self, params: np.ndarray, ctx: EffectContext) -> np.ndarray:
        """(N, 3) additive offset of the latched controller X, Y, Z, mm."""
        p = self._check(params)
        if self._touch is None:
            return np.zeros((len(ctx), 3))
        return self._touch(p, ctx)


def combine_motion_errors(*maps: Mapping[str, MotionErrorFn]) -> dict[str, MotionErrorFn]:
    """Sum the component-error functions of several effects acting on the same axes (small
    errors superpose to first order, which is how ISO 230-1 component errors are defined)."""
    per_axis: dict[str, list[MotionErrorFn]] = {}
    for m in maps:
        for k, f in m.items():
            per_axis.setdefault(k, []).append(f)

    def summed(fs: list[MotionErrorFn]) -> MotionErrorFn:
        return lambda q: np.sum([np.asarray(f(q), float) for f in fs], axis=0)

    return {k: (fs[0] if len(fs) == 1 else summed(fs)) for k, fs in per_axis.items()}


def need_axis(machine: Machine, family: str, axis: str | None, letters: str) -> str:
    """The axis letter a family is built on, checked against ``letters`` and the machine."""
    if axis is None or axis.upper() not in letters or axis.upper() not in machine.axes:
        have = [a for a in machine.axes if a in letters]
        raise ValueError(f"{family}: axis must be one of {have}, got {axis!r}")
    return axis.upper()

