"""Parametric models of effects the twin may lack, shared by the simulator and the gap diagnosis.

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

Polynomials are in the model joint value expressed in metres (seed 004 Eqs (4)-(6):
parametric errors as polynomials in the axis position); constant and — for straightness —
linear terms are excluded because they are link errors (offsets, squareness) already estimated
with the setup (thesis §3.5, Table B.2), so including them would only duplicate twin parameters.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from identification.kinematics import (
    LINEAR_LETTERS,
    ROTARY_LETTERS,
    ChainState,
    Machine,
    MotionErrorFn,
    frames,
    rotary_columns,
    to_model,
)

FAMILIES = (
    "thermal_drift",
    "linear_scale",
    "straightness",
    "angular_motion",
    "rotary_positioning",
    "rotary_error_motion",
    "gravity_sag",
    "probe_pretravel",
    "artefact_instability",
)

_UM = 1e-3  # µm → mm
_URAD = 1e-6  # µrad → rad
_XYZ = "XYZ"
_ABC = "ABC"


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


# ------------------------------------------------------------------ helpers


def _need_axis(machine: Machine, family: str, axis: str | None, letters: str) -> str:
    if axis is None or axis.upper() not in letters or axis.upper() not in machine.axes:
        have = [a for a in machine.axes if a in letters]
        raise ValueError(f"{family}: axis must be one of {have}, got {axis!r}")
    return axis.upper()


def _perp(index: int) -> list[int]:
    return [i for i in range(3) if i != index]


def _poly_motion(letter: str, comps: list[int], powers: tuple[int, ...], to_model_unit: float,
                 p: np.ndarray) -> dict[str, MotionErrorFn]:
    """Component errors sum_k p[c, k] * (q / 1 m)^powers[k] on the listed components."""
    coef = p.reshape(len(comps), len(powers)) * to_model_unit

    def fn(q: np.ndarray) -> np.ndarray:
        qm = np.asarray(q, float) * 1e-3  # mm → m
        out = np.zeros((qm.shape[0], 6))
        basis = np.stack([qm**k for k in powers], axis=1)
        for i, c in enumerate(comps):
            out[:, c] = basis @ coef[i]
        return out

    return {letter: fn}


def default_gravity(machine: Machine) -> np.ndarray:
    """Gravity direction in the foundation frame when the machine file does not give it (its
    ``gravity`` key, passed as the ``gravity_dir`` option). A heuristic: a workpiece-side rotary
    axis turning about Y next to the foundation is the rotary table of a horizontal machine
    (thesis WCBXFZYT, seed 001 wBZfXYCt): Y is vertical, gravity −Y. Otherwise a vertical
    machine: gravity −Z. It is wrong for a vertical machine whose trunnion tilts about Y
    (LinuxCNC xyzbc-trt): such a machine file must say ``gravity: [0, 0, -1]``."""
    rot = [a for a in machine.workpiece_chain if a in ROTARY_LETTERS]
    if rot and machine.axes[rot[0]].index == 1:
        return np.array([0.0, -1.0, 0.0])
    return np.array([0.0, 0.0, -1.0])


def unit_vector(v: Sequence[float] | np.ndarray, what: str) -> np.ndarray:
    """A finite, non-zero 3-vector, normalised; ValueError naming ``what`` otherwise."""
    try:
        a = np.asarray(v, float).reshape(-1)
    except (TypeError, ValueError):
        raise ValueError(f"{what}: expected 3 numbers, got {v!r}") from None
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{what}: expected 3 finite numbers, got {v!r}")
    n = float(np.linalg.norm(a))
    if n < 1e-9:
        raise ValueError(f"{what}: must not be the zero vector")
    return a / n


def default_rod_direction(machine: Machine) -> np.ndarray:
    """Rods stand along +z of the last workpiece frame: the project's table convention (the
    pallet face is a plane z = surface_z_mm of that frame, balls on rods above it; DESIGN.md,
    machine file ``table``)."""
    return np.array([0.0, 0.0, 1.0])


def workpiece_rotation(machine: Machine, b_deg: np.ndarray, c_deg: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation foundation ← last workpiece frame of the nominal chain."""
    n = np.asarray(b_deg).shape[0]
    q = to_model(machine, rotary_columns(machine, b_deg, c_deg))
    q.update({a: np.zeros(n) for a in LINEAR_LETTERS if a in machine.axes})
    f_w, _ = frames(machine, q, ChainState())
    return f_w[:, :3, :3]


# ------------------------------------------------------------------ the families


def _thermal_drift(machine: Machine, axis: str | None, model: str = "linear",
                   tau_h: float | None = None) -> Effect:
    # Seed 002 §3.3.4: thermal drift appears as an offset of the measured position that grows
    # with time from the reference thermal state; here per controller axis, linear (µm/h) or
    # first-order exponential (amplitude µm, time constant h).
    letter = _need_axis(machine, "thermal_drift", axis, LINEAR_LETTERS)
    col = _XYZ.index(letter)
    if model == "linear":
        names, units = (f"drift_{letter}_rate",), ("um/h",)

        def shape(p: np.ndarray, t_h: np.ndarray) -> np.ndarray:
            return p[0] * t_h
    elif model == "exponential" and tau_h is None:
        names, units = (f"drift_{letter}_amplitude", f"drift_{letter}_tau"), ("um", "h")

        def shape(p: np.ndarray, t_h: np.ndarray) -> np.ndarray:
            return p[0] * (1.0 - np.exp(-t_h / max(p[1], 1e-6)))
    elif model == "exponential":
        names, units = (f"drift_{letter}_amplitude",), ("um",)

        def shape(p: np.ndarray, t_h: np.ndarray) -> np.ndarray:
            return p[0] * (1.0 - np.exp(-t_h / tau_h))
    else:
        raise ValueError(f"thermal_drift: model must be 'linear' or 'exponential', got {model!r}")

    def touch(p: np.ndarray, ctx: EffectContext) -> np.ndarray:
        out = np.zeros((len(ctx), 3))
        out[:, col] = shape(p, np.asarray(ctx.t_s, float) / 3600.0) * _UM
        return out

    return Effect("thermal_drift", letter, names, units, _touch=touch,
                  linear=not (model == "exponential" and tau_h is None),
                  note="seed 002 §3.3.4: drift of the reading from the reference thermal state")


def _linear_scale(machine: Machine, axis: str | None) -> Effect:
    # Seed 003 §2 / ISO 230-1: linear positioning error EXX = s · x (µm/m), along the axis.
    letter = _need_axis(machine, "linear_scale", axis, LINEAR_LETTERS)
    d = np.asarray(machine.axes[letter].direction, float)

    def motion(p: np.ndarray) -> dict[str, MotionErrorFn]:
        s = p[0] * 1e-6

        def fn(q: np.ndarray) -> np.ndarray:
            out = np.zeros((np.shape(q)[0], 6))
            out[:, :3] = (s * np.asarray(q, float))[:, None] * d[None, :]
            return out

        return {letter: fn}

    return Effect("linear_scale", letter, (f"E{letter}{letter}",), ("um/m",), _motion=motion,
                  note="seed 003 §5.2: linear positioning error, proportional to position")


def _straightness(machine: Machine, axis: str | None, powers: tuple[int, ...] = (2, 3)) -> Effect:
    # Seed 004 §2: straightness as a polynomial in the axis position; the linear term is a
    # squareness (a link error of the twin) and the constant an offset: both excluded.
    letter = _need_axis(machine, "straightness", axis, LINEAR_LETTERS)
    if any(k < 2 for k in powers):
        raise ValueError("straightness: powers must be >= 2 (the linear term is a squareness)")
    comps = _perp(_XYZ.index(letter))
    names = tuple(f"E{_XYZ[c]}{letter}_q{k}" for c in comps for k in powers)
    units = tuple(f"um/m^{k}" for _ in comps for k in powers)
    return Effect("straightness", letter, names, units,
                  _motion=lambda p: _poly_motion(letter, comps, powers, _UM, p),
                  note="seed 004 Eqs (4)-(6): straightness polynomial, terms of power >= 2")


def _angular_motion(machine: Machine, axis: str | None, powers: tuple[int, ...] = (1, 2)) -> Effect:
    # Seed 004 Eqs (4)-(6) / seed 003 §5.2: angular errors EAX, EBX, ECX (pitch, yaw, roll) as
    # polynomials in the position; the constant is a link (orientation) error, excluded.
    letter = _need_axis(machine, "angular_motion", axis, LINEAR_LETTERS)
    if any(k < 1 for k in powers):
        raise ValueError("angular_motion: powers must be >= 1 (the constant is a link error)")
    comps = [3, 4, 5]
    names = tuple(f"E{_ABC[c - 3]}{letter}_q{k}" for c in comps for k in powers)
    units = tuple("urad/m" if k == 1 else f"urad/m^{k}" for _ in comps for k in powers)
    return Effect("angular_motion", letter, names, units,
                  _motion=lambda p: _poly_motion(letter, comps, powers, _URAD, p),
                  note="seed 004 Eqs (4)-(6): angular motion polynomial, terms of power >= 1")


def _rotary_positioning(machine: Machine, axis: str | None, orders: tuple[int, ...] = (1, 2)
                        ) -> Effect:
    # ISO 230-1 angular positioning error of a rotary axis (ECC, EBB …): a slope (encoder scale,
    # µrad per rad of rotation) plus harmonics of the angle (µrad). The constant is the zero
    # offset, absorbed by the ball setup (it rotates every ball alike).
    letter = _need_axis(machine, "rotary_positioning", axis, ROTARY_LETTERS)
    comp = 3 + machine.axes[letter].index
    names = [f"E{letter}{letter}_slope"]
    units = ["urad/rad"]
    for k in orders:
        names += [f"E{letter}{letter}_cos{k}", f"E{letter}{letter}_sin{k}"]
        units += ["urad", "urad"]

    def motion(p: np.ndarray) -> dict[str, MotionErrorFn]:
        def fn(q: np.ndarray) -> np.ndarray:
            q = np.asarray(q, float)
            e = p[0] * q
            for i, k in enumerate(orders):
                e = e + p[1 + 2 * i] * np.cos(k * q) + p[2 + 2 * i] * np.sin(k * q)
            out = np.zeros((q.shape[0], 6))
            out[:, comp] = e * _URAD
            return out

        return {letter: fn}

    return Effect("rotary_positioning", letter, tuple(names), tuple(units), _motion=motion,
                  note="ISO 230-1 / seed 003 §5.2: angular positioning error of a rotary axis")


def _rotary_error_motion(machine: Machine, axis: str | None, orders: tuple[int, ...] = (2,),
                         components: tuple[str, ...] = ("radial", "axial", "tilt")) -> Effect:
    # ISO 230-7 error motion of a rotary axis as harmonics of its angle, expressed in the moving
    # axis frame (components applied after the motion). Order 0 is a link (location) error and
    # order 1 of radial/tilt is an eccentricity/wobble equivalent to one too: orders >= 2 only.
    letter = _need_axis(machine, "rotary_error_motion", axis, ROTARY_LETTERS)
    if any(k < 2 for k in orders):
        raise ValueError("rotary_error_motion: orders must be >= 2 (0 and 1 are link errors)")
    idx = machine.axes[letter].index
    comp_of = {"radial": [c for c in _perp(idx)], "axial": [idx],
               "tilt": [3 + c for c in _perp(idx)]}
    comps = [c for name in components for c in comp_of[name]]
    names, units = [], []
    for c in comps:
        iso = f"E{(_XYZ + _ABC)[c]}{letter}"
        for k in orders:
            names += [f"{iso}_cos{k}", f"{iso}_sin{k}"]
            units += ["um" if c < 3 else "urad"] * 2

    def motion(p: np.ndarray) -> dict[str, MotionErrorFn]:
        coef = p.reshape(len(comps), len(orders), 2)

        def fn(q: np.ndarray) -> np.ndarray:
            q = np.asarray(q, float)
            out = np.zeros((q.shape[0], 6))
            for i, c in enumerate(comps):
                unit = _UM if c < 3 else _URAD
                for j, k in enumerate(orders):
                    out[:, c] += (coef[i, j, 0] * np.cos(k * q) + coef[i, j, 1] * np.sin(k * q)) \
                        * unit
            return out

        return {letter: fn}

    return Effect("rotary_error_motion", letter, tuple(names), tuple(units), _motion=motion,
                  note="ISO 230-7: radial/axial/tilt error motion harmonics of order >= 2")


def _gravity_sag(machine: Machine, axis: str | None, gravity_dir: tuple | None = None,
                 rod_dir: tuple | None = None) -> Effect:
    # Thesis §3.3: the rods bend under the ball's weight (1.49 µm computed for the 152 mm rod).
    # A cantilever with an end load deflects by F L^3 / (3 E I) along the load component
    # perpendicular to the rod: ball shift = s · (L / 100 mm)^3 · g_perp, with g_perp the part of
    # the unit gravity vector (foundation frame, rotated into the last workpiece frame) normal to
    # the rod. Its length is sin(angle rod–gravity): it varies with the tilt on a vertical
    # trunnion machine (−Z gravity, rods vertical at A = 0) and is constant, but turns with C in
    # the workpiece frame, on the horizontal thesis machine (−Y gravity, rods horizontal).
    # ``s`` = sag of a 100 mm rod held perpendicular to gravity, µm.
    if axis is not None:
        raise ValueError("gravity_sag: takes no axis")
    g = unit_vector(gravity_dir, "gravity_dir") if gravity_dir is not None \
        else default_gravity(machine)
    u = np.asarray(rod_dir if rod_dir is not None else default_rod_direction(machine), float)
    u = u / np.linalg.norm(u)

    def ball(p: np.ndarray, ctx: EffectContext) -> np.ndarray:
        r = workpiece_rotation(machine, np.asarray(ctx.b_deg), np.asarray(ctx.c_deg))
        g_w = np.einsum("nji,j->ni", r, g)  # R^T g: gravity in the last workpiece frame
        g_perp = g_w - (g_w @ u)[:, None] * u[None, :]
        lever = (np.asarray(ctx.rod_length_mm, float) / 100.0) ** 3
        return p[0] * _UM * lever[:, None] * g_perp

    return Effect("gravity_sag", None, ("sag_100mm",), ("um",), _ball=ball,
                  note="thesis §3.3: rod deflection under the ball weight, ∝ L^3 · sin(tilt)")


def _probe_pretravel(machine: Machine, axis: str | None, n_directions: int = 5) -> Effect:
    # Thesis §3.4: the probe latches after a pre-travel along the approach direction, which
    # depends on the direction (lobing). The latched position is past the contact point:
    # offset = p(touch) · direction. A part identical for all directions only changes the fitted
    # radius; the rest moves every centre by the same machine-frame vector and ends in the
    # stylus-tip setup ("interpreted as a stylus tip centre setup error", thesis §3.4); what
    # survives is the sphere-fit residual pattern (5 touches, 4 sphere parameters: 1 dof).
    if axis is not None:
        raise ValueError("probe_pretravel: takes no axis")
    names = tuple(f"pretravel_dir{k}" for k in range(1, n_directions + 1))

    def touch(p: np.ndarray, ctx: EffectContext) -> np.ndarray:
        k = np.asarray(ctx.touch, int)
        if np.any((k < 1) | (k > n_directions)):
            raise ValueError(f"probe_pretravel: touch numbers must be 1..{n_directions}")
        d = np.asarray(ctx.direction, float)
        d = d / np.linalg.norm(d, axis=1, keepdims=True)
        return (p[k - 1] * _UM)[:, None] * d

    return Effect("probe_pretravel", None, names, ("um",) * n_directions, _touch=touch,
                  note="thesis §3.4: pre-travel by approach direction (lobing)")


def _artefact_instability(machine: Machine, axis: str | None, ball_index: int | None = None,
                          n_balls: int | None = None) -> Effect:
    # Thesis §3.3: the method needs the artefact stable during a session; a ball creeping on its
    # rod moves at a constant velocity (µm/h) in the last workpiece frame. The position at t = 0
    # is a setup error, so only the velocity is a new parameter. ``axis`` names the ball (its id);
    # ``ball_index`` is its index in the artefact. Without a ball, every ball creeps (n_balls).
    if ball_index is None:
        if n_balls is None:
            raise ValueError("artefact_instability: give ball_index (one ball) or n_balls (all)")
        balls = list(range(n_balls))
    else:
        balls = [int(ball_index)]
    names = tuple(f"creep_{axis if len(balls) == 1 and axis else f'ball{b}'}_{a}"
                  for b in balls for a in "xyz")

    def ball_fn(p: np.ndarray, ctx: EffectContext) -> np.ndarray:
        v = p.reshape(len(balls), 3) * _UM
        out = np.zeros((len(ctx), 3))
        t_h = np.asarray(ctx.t_s, float) / 3600.0
        for i, b in enumerate(balls):
            m = np.asarray(ctx.ball) == b
            out[m] = t_h[m, None] * v[i][None, :]
        return out

    return Effect("artefact_instability", axis, names, ("um/h",) * len(names), _ball=ball_fn,
                  note="thesis §3.3: artefact stability during a session; creep in time")


_FACTORIES = {
    "thermal_drift": _thermal_drift,
    "linear_scale": _linear_scale,
    "straightness": _straightness,
    "angular_motion": _angular_motion,
    "rotary_positioning": _rotary_positioning,
    "rotary_error_motion": _rotary_error_motion,
    "gravity_sag": _gravity_sag,
    "probe_pretravel": _probe_pretravel,
    "artefact_instability": _artefact_instability,
}


def make_effect(family: str, axis: str | None, machine: Machine, **options) -> Effect:
    """Build one effect. Options per family:

    thermal_drift(model="linear"|"exponential", tau_h=None); straightness(powers=(2, 3));
    angular_motion(powers=(1, 2)); rotary_positioning(orders=(1, 2));
    rotary_error_motion(orders=(2,), components=("radial", "axial", "tilt"));
    gravity_sag(gravity_dir=None, rod_dir=None); probe_pretravel(n_directions=5);
    artefact_instability(ball_index=None, n_balls=None) — axis = the ball id or None.
    """
    if family not in _FACTORIES:
        raise ValueError(f"unknown effect family {family!r}; expected one of {FAMILIES}")
    try:
        return _FACTORIES[family](machine, axis, **options)
    except TypeError as e:  # unknown option: say which family and which options exist
        raise ValueError(f"{family}: {e}") from None


def _full_turn(axis) -> bool:
    lo, hi = axis.travel
    return hi - lo >= 360.0


def library(machine: Machine, ball_ids: list[str],
            gravity_dir: Sequence[float] | None = None) -> list[Effect]:
    """The candidate library of the gap diagnosis: every family on every axis it applies to.
    ``gravity_dir``: the machine file's gravity (foundation frame); None: ``default_gravity``."""
    lin = [a for a in machine.linear_axes]
    rot = machine.rotary_axes
    out: list[Effect] = []
    out += [make_effect("thermal_drift", a, machine) for a in sorted(lin)]
    out += [make_effect("linear_scale", a, machine) for a in sorted(lin)]
    out += [make_effect("straightness", a, machine) for a in sorted(lin)]
    out += [make_effect("angular_motion", a, machine) for a in sorted(lin)]
    out += [make_effect("rotary_positioning", a, machine) for a in rot]
    # Harmonics 2 and 3 on a full-turn axis (a rotary table), 2 only on a tilting axis whose
    # limited range cannot separate higher orders from the polynomial-like low ones.
    out += [make_effect("rotary_error_motion", a, machine,
                        orders=(2, 3) if _full_turn(machine.axes[a]) else (2,)) for a in rot]
    out.append(make_effect("gravity_sag", None, machine, gravity_dir=gravity_dir))
    out.append(make_effect("probe_pretravel", None, machine))
    out += [make_effect("artefact_instability", b, machine, ball_index=i)
            for i, b in enumerate(ball_ids)]
    return out
