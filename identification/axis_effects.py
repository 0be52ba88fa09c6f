"""Effect families that are component errors of a machine axis (ISO 230-1 / 230-7).

Polynomials are in the model joint value expressed in metres (seed 004 Eqs (4)-(6):
parametric errors as polynomials in the axis position); constant and — for straightness —
linear terms are excluded because they are link errors (offsets, squareness) already estimated
with the setup (thesis §3.5, Table B.2), so including them would only duplicate twin parameters.
"""

from __future__ import annotations

import numpy as np

from identification.effect_types import ABC, UM, URAD, XYZ, Effect, need_axis
from identification.kinematics import LINEAR_LETTERS, ROTARY_LETTERS, Machine, MotionErrorFn


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


def rotary_positioning(machine: Machine, axis: str | None, orders: tuple[int, ...] = (1, 2)
                        ) -> Effect:
    # ISO 230-1 angular positioning error of a rotary axis (ECC, EBB …): a slope (encoder scale,
    # µrad per rad of rotation) plus harmonics of the angle (µrad). The constant is the zero
    # offset, absorbed by the ball setup (it rotates every ball alike).
    letter = need_axis(machine, "rotary_positioning", axis, ROTARY_LETTERS)
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
            out[:, comp] = e * URAD
            return out

        return {letter: fn}

    return Effect("rotary_positioning", letter, tuple(names), tuple(units), _motion=motion,
                  note="ISO 230-1 / seed 003 §5.2: angular positioning error of a rotary axis")


def rotary_error_motion(machine: Machine, axis: str | None, orders: tuple[int, ...] = (2,),
                         components: tuple[str, ...] = ("radial", "axial", "tilt")) -> Effect:
    # ISO 230-7 error motion of a rotary axis as harmonics of its angle, expressed in the moving
    # axis frame (components applied after the motion). Order 0 is a link (location) error and
    # order 1 of radial/tilt is an eccentricity/wobble equivalent to one too: orders >= 2 only.
    letter = need_axis(machine, "rotary_error_motion", axis, ROTARY_LETTERS)
    if any(k < 2 for k in orders):
        raise ValueError("rotary_error_motion: orders must be >= 2 (0 and 1 are link errors)")
    idx = machine.axes[letter].index
    comp_of = {"radial": [c for c in _perp(idx)], "axial": [idx],
               "tilt": [3 + c for c in _perp(idx)]}
    comps = [c for name in components for c in comp_of[name]]
    names, units = [], []
    for c in comps:
        iso = f"E{(XYZ + ABC)[c]}{letter}"
        for k in orders:
            names += [f"{iso}_cos{k}", f"{iso}_sin{k}"]
            units += ["um" if c < 3 else "urad"] * 2

    def motion(p: np.ndarray) -> dict[str, MotionErrorFn]:
        coef = p.reshape(len(comps), len(orders), 2)

        def fn(q: np.ndarray) -> np.ndarray:
            q = np.asarray(q, float)
            out = np.zeros((q.shape[0], 6))
            for i, c in enumerate(comps):
                unit = UM if c < 3 else URAD
                for j, k in enumerate(orders):
                    out[:, c] += (coef[i, j, 0] * np.cos(k * q) + coef[i, j, 1] * np.sin(k * q)) \
                        * unit
            return out

        return {letter: fn}

    return Effect("rotary_error_motion", letter, tuple(names), tuple(units), _motion=motion,
                  note="ISO 230-7: radial/axial/tilt error motion harmonics of order >= 2")

