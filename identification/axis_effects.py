"""Effect families that are component errors of a machine axis (ISO 230-1 / 230-7).

Polynomials are in the model joint value expressed in metres (seed 004 Eqs (4)-(6):
parametric errors as polynomials in the axis position); constant and — for straightness —
linear terms are excluded because they are link errors (offsets, squareness) already estimated
with the setup (thesis §3.5, Table B.2), so including them would only duplicate twin parameters.
Rotary error motion (ISO 230-7) is given in the axis' fixed frame and mapped to the moving-frame
6-vector the chain applies (``fixed_to_moving``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from identification.effect_types import ABC, UM, URAD, XYZ, Effect, need_axis
from identification.kinematics import LINEAR_LETTERS, ROTARY_LETTERS, Axis, Machine, MotionErrorFn


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


def linear_scale(machine: Machine, axis: str | None) -> Effect:
    # Seed 003 §2 / ISO 230-1: linear positioning error EXX = s · x (µm/m), along the axis.
    letter = need_axis(machine, "linear_scale", axis, LINEAR_LETTERS)
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


def straightness(machine: Machine, axis: str | None, powers: tuple[int, ...] = (2, 3)) -> Effect:
    # Seed 004 §2: straightness as a polynomial in the axis position; the linear term is a
    # squareness (a link error of the twin) and the constant an offset: both excluded.
    letter = need_axis(machine, "straightness", axis, LINEAR_LETTERS)
    if any(k < 2 for k in powers):
        raise ValueError("straightness: powers must be >= 2 (the linear term is a squareness)")
    comps = _perp(XYZ.index(letter))
    names = tuple(f"E{XYZ[c]}{letter}_q{k}" for c in comps for k in powers)
    units = tuple(f"um/m^{k}" for _ in comps for k in powers)
    return Effect("straightness", letter, names, units,
                  _motion=lambda p: _poly_motion(letter, comps, powers, UM, p),
                  note="seed 004 Eqs (4)-(6): straightness polynomial, terms of power >= 2")


def angular_motion(machine: Machine, axis: str | None, powers: tuple[int, ...] = (1, 2)) -> Effect:
    # Seed 004 Eqs (4)-(6) / seed 003 §5.2: angular errors EAX, EBX, ECX (pitch, yaw, roll) as
    # polynomials in the position; the constant is a link (orientation) error, excluded.
    letter = need_axis(machine, "angular_motion", axis, LINEAR_LETTERS)
    if any(k < 1 for k in powers):
        raise ValueError("angular_motion: powers must be >= 1 (the constant is a link error)")
    comps = [3, 4, 5]
    names = tuple(f"E{ABC[c - 3]}{letter}_q{k}" for c in comps for k in powers)
    units = tuple("urad/m" if k == 1 else f"urad/m^{k}" for _ in comps for k in powers)
    return Effect("angular_motion", letter, names, units,
                  _motion=lambda p: _poly_motion(letter, comps, powers, URAD, p),
                  note="seed 004 Eqs (4)-(6): angular motion polynomial, terms of power >= 1")


def rotary_positioning(machine: Machine, axis: str | None, orders: tuple[int, ...] = (1, 2),
                       slope: bool = True) -> Effect:
    # ISO 230-1 angular positioning error of a rotary axis (ECC, EBB …): a slope (encoder scale,
    # µrad per rad of rotation) plus harmonics of the angle (µrad). The constant is the zero
    # offset, absorbed by the ball setup (it rotates every ball alike). ``slope=False`` with one
    # order: a single harmonic alone (an eccentric or two-fold encoder error, 2 parameters).
    letter = need_axis(machine, "rotary_positioning", axis, ROTARY_LETTERS)
    if (not orders and not slope) or any(k < 1 for k in orders):
        raise ValueError("rotary_positioning: orders must be >= 1 (the constant is the zero "
                         "offset), with a slope or at least one order")
    comp = 3 + machine.axes[letter].index
    names = [f"E{letter}{letter}_slope"] if slope else []
    units = ["urad/rad"] if slope else []
    off = 1 if slope else 0
    for k in orders:
        names += [f"E{letter}{letter}_cos{k}", f"E{letter}{letter}_sin{k}"]
        units += ["urad", "urad"]

    def motion(p: np.ndarray) -> dict[str, MotionErrorFn]:
        def fn(q: np.ndarray) -> np.ndarray:
            q = np.asarray(q, float)
            e = p[0] * q if slope else np.zeros_like(q)
            for i, k in enumerate(orders):
                e = e + p[off + 2 * i] * np.cos(k * q) + p[off + 1 + 2 * i] * np.sin(k * q)
            out = np.zeros((q.shape[0], 6))
            out[:, comp] = e * URAD
            return out

        return {letter: fn}

    return Effect("rotary_positioning", letter, tuple(names), tuple(units), _motion=motion,
                  note="ISO 230-1 / seed 003 §5.2: angular positioning error of a rotary axis")


# ISO 230-7 error motion of a rotary axis, in its FIXED (non-rotating) frame — the frame of the
# stator, i.e. the axis' parent frame in the chain — at the axis reference point p (point_mm):
# radial δ_i(θ), δ_j(θ), axial δ_axis(θ) and tilt ε_i(θ), ε_j(θ) (i, j ⟂ the axis) relative to the
# axis average line, each Σ_k a_k cos kθ + b_k sin kθ of the axis angle θ (model joint value).
# The chain applies motion errors in the moving frame (kinematics.axis_htm), i.e. Rᵀ(θ)·δ. With
# u = δ_i + i·δ_j, Rᵀ multiplies by e^{−iθ}: a fixed order k, u = α e^{ikθ} + β e^{−ikθ}, is seen
# in the moving frame as α e^{i(k−1)θ} + β e^{−i(k+1)θ} — orders k−1 (co-rotating part α) and
# k+1 (counter-rotating part β); the axial component is not rotated. Hence, as the tests prove on
# the full-turn C and the tilting B (tests/test_rotary_error_motion.py):
# * order 0: a location (link) error, or a setup error where it commutes with the rotation
#   (axial shift, tilt about the axis itself, offsets absorbed by the tip setup) — absorbed;
# * order 1 radial/tilt, co-rotating part δ = R(θ)·v: constant in the moving frame — the
#   eccentricity (wobble) of the rotor, taken up by the ball setup — absorbed;
# * order 1 counter-rotating part (moving order 2) and axial order 1: NOT absorbed. ISO 230-7
#   drops the fundamental of radial motion measured in one fixed sensitive direction, where it
#   cannot be told from the centring error; probing balls in 3-D sees both directions at once;
# * order ≥ 2: not absorbed (the 2nd harmonic of C is order 1 and 3 in the moving frame).
# On a tilting axis (limited range) the algebra is the same, but harmonics are far from
# orthogonal: the diagnosis keeps only the directions the plan sees (gap.linear.projected).
ERROR_MOTION_COMPONENTS = ("radial", "axial", "tilt")
MAX_ERROR_MOTION_ORDER = 36  # a 10° period: finer than any plan of indexed poses resolves


def _perp_cyclic(index: int) -> tuple[int, int]:
    """The two directions (i, j) perpendicular to ``index`` with (index, i, j) cyclic, so that
    a rotation by θ about ``index`` turns the complex number v_i + i·v_j by e^{iθ}."""
    return [(1, 2), (2, 0), (0, 1)][index]


def fixed_to_moving(axis: Axis, q: np.ndarray, e_fixed: np.ndarray) -> np.ndarray:
    """(N, 6) error motion of a rotary axis given in its fixed frame → the moving-frame 6-vector
    the chain applies after the motion (kinematics.axis_htm), to first order.

    The fixed-frame motion E_f acts about the axis reference point p (``point_mm``) before the
    rotation R(q): T(p)·E_f·R·T(−p) = [T(p)·R·T(−p)]·E_m, so E_m = T(p)·Rᵀ·E_f·R·T(−p): rotation
    ε_m = Rᵀε_f, translation δ_m = Rᵀδ_f − ε_m × p (second-order terms ~ε² ≈ 1e-10 dropped)."""
    q = np.asarray(q, float)
    e = np.asarray(e_fixed, float).reshape(q.shape[0], 6)
    idx = axis.index
    i, j = _perp_cyclic(idx)
    th = float(np.sign(axis.direction[idx])) * q  # kinematics: an axis along −z turns by −q
    c, s = np.cos(th), np.sin(th)
    out = e.copy()
    for off in (0, 3):  # Rᵀ on the translation, then on the rotation vector
        out[:, off + i] = c * e[:, off + i] + s * e[:, off + j]
        out[:, off + j] = -s * e[:, off + i] + c * e[:, off + j]
    p = np.asarray(axis.point_mm, float)
    if p.any():
        out[:, :3] -= np.cross(out[:, 3:], p)
    return out


def error_motion_slots(axis: Axis, component: str) -> list[int]:
    """Slots of [EX, EY, EZ, EA, EB, EC] a component acts on (ascending: ISO name order)."""
    i, j = sorted(_perp_cyclic(axis.index))
    return {"radial": [i, j], "axial": [axis.index], "tilt": [3 + i, 3 + j]}[component]


def order1_params(axis: Axis, component: str, v: Sequence[float], co_rotating: bool
                  ) -> dict[str, float]:
    """Parameters {name: value} of an order-1 radial or tilt error motion (the effect
    ``fixed_error_motion(…, (1,), (component,))``) whose vector at θ = 0 is v = (v_i, v_j) in
    the cyclic perpendicular directions (i, j): co-rotating, δ = R(θ)·v — an eccentricity of the
    rotor, constant in the moving frame — or counter-rotating, δ = Rᵀ(θ)·v (moving order 2)."""
    vi, vj = (float(x) for x in v)
    sg = float(np.sign(axis.direction[axis.index]))  # θ = sg·q: cos θ = cos q, sin θ = sg sin q
    t = -1.0 if co_rotating else 1.0
    # δ_i = v_i cos θ ∓ v_j sin θ, δ_j = v_j cos θ ± v_i sin θ (upper sign: co-rotating).
    i, j = (k + (3 if component == "tilt" else 0) for k in _perp_cyclic(axis.index))
    ni, nj = (f"E{(XYZ + ABC)[k]}{axis.letter}" for k in (i, j))
    return {f"{ni}_cos1": vi, f"{ni}_sin1": t * sg * vj,
            f"{nj}_cos1": vj, f"{nj}_sin1": -t * sg * vi}


def fixed_error_motion(machine: Machine, letter: str, orders: tuple[int, ...],
                       components: tuple[str, ...]) -> Effect:
    """The fixed-frame harmonic family for any orders ≥ 0 (order 0: one constant ``_cos0`` per
    slot), unchecked: ``rotary_error_motion`` is the public, checked one; orders 0 and 1 serve
    the proof of what links and setup absorb."""
    ax = machine.axes[letter]
    # One term per (slot, order, cos|sin): the slot of the 6-vector, k, and the trig function.
    terms = [(c, k, trig) for name in components for c in error_motion_slots(ax, name)
             for k in orders for trig in (("cos",) if k == 0 else ("cos", "sin"))]
    names = tuple(f"E{(XYZ + ABC)[c]}{letter}_{trig}{k}" for c, k, trig in terms)
    units = tuple("um" if c < 3 else "urad" for c, _, _ in terms)

    def motion(p: np.ndarray) -> dict[str, MotionErrorFn]:
        def fn(q: np.ndarray) -> np.ndarray:
            q = np.asarray(q, float)
            e = np.zeros((q.shape[0], 6))
            for v, (c, k, trig) in zip(p, terms, strict=True):
                wave = np.cos(k * q) if trig == "cos" else np.sin(k * q)
                e[:, c] += v * (UM if c < 3 else URAD) * wave
            return fixed_to_moving(ax, q, e)

        return {letter: fn}

    return Effect("rotary_error_motion", letter, names, units, _motion=motion,
                  note="ISO 230-7: radial/axial/tilt error motion in the fixed frame, "
                       "harmonics of the axis angle")


def _checked(name: str, values: object, ok: Callable[[object], bool], expected: str) -> tuple:
    if isinstance(values, str | bytes) or not isinstance(values, Sequence) or not values:
        raise ValueError(f"rotary_error_motion: {name}: expected a non-empty list of {expected}, "
                         f"got {values!r}")
    bad = [v for v in values if not ok(v)]
    if bad:
        raise ValueError(f"rotary_error_motion: {name}: {bad} not {expected}")
    if len(set(values)) != len(values):
        raise ValueError(f"rotary_error_motion: {name}: {list(values)} has repeats")
    return tuple(values)


def rotary_error_motion(machine: Machine, axis: str | None, orders: Sequence[int] = (2,),
                         components: Sequence[str] = ERROR_MOTION_COMPONENTS) -> Effect:
    # ISO 230-7 radial, axial and tilt error motion in the fixed frame (see above). Order 0 is
    # rejected: it is wholly a link or setup error. Order 1 is accepted: only its co-rotating
    # radial/tilt part is absorbed (the diagnosis reports the visible part, minimum norm).
    letter = need_axis(machine, "rotary_error_motion", axis, ROTARY_LETTERS)
    ords = _checked("orders", orders, lambda k: isinstance(k, int) and not isinstance(k, bool)
                    and 1 <= k <= MAX_ERROR_MOTION_ORDER,
                    f"whole numbers 1..{MAX_ERROR_MOTION_ORDER} (0 is a link error)")
    comps = _checked("components", components, lambda c: c in ERROR_MOTION_COMPONENTS,
                     f"one of {list(ERROR_MOTION_COMPONENTS)}")
    return fixed_error_motion(machine, letter, ords, comps)
