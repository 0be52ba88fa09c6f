"""Systematic errors of a linear axis outside the gap library: a cyclic error and a local bump.

Both are component errors of one linear axis (ISO 230-1: positioning E<X>X along it, or
straightness E<Y>X, E<Z>X across it) that a smooth polynomial (``axis_effects``) cannot follow:

* ``cyclic_error`` — a periodic positioning or straightness error of period ``period_mm``,
  δ(x) = a·cos(2πx/P) + b·sin(2πx/P) µm at the axis position x (controller coordinate): the
  ball screw's pitch error, a rack or scale period (ISO 230-2 calls the short-period part of the
  positioning error "periodic"; ISO 230-1 Annex A lists it among the linear axes' errors);
* ``local_bump`` — a local error of height h µm over ``width_mm`` around ``centre_mm``, a raised
  cosine h·½(1 + cos(2π(x − c)/w)) for |x − c| ≤ w/2, else 0: a worn or damaged stretch of a
  guideway, a chip under a scale.

They are the simulator's (``simulators.truth``, errors file ``effects``) and the gap
self-check's truth; the gap diagnosis does not offer them as candidates. It must find them as
located structure along the axis (``gap.structure``), not absorb them into its floor.
"""

from __future__ import annotations

import math

import numpy as np

from identification.effect_types import UM, XYZ, Effect, need_axis
from identification.kinematics import LINEAR_LETTERS, Machine, MotionErrorFn

OUTSIDE_NOTE = "outside the gap library: found as located structure along the axis"


def _component(machine: Machine, family: str, letter: str, component: str | None
               ) -> tuple[str, np.ndarray | int]:
    """The ISO 230-1 name of the error and where it acts: the axis direction (positioning)
    or a frame component index (straightness)."""
    name = component or f"E{letter}{letter}"
    if len(name) != 3 or name[0] != "E" or name[1] not in XYZ or name[2] != letter:
        raise ValueError(f"{family}: component must be E{letter}{letter} (positioning) or "
                         f"E<X|Y|Z>{letter} (straightness), got {component!r}")
    if name[1] == letter:
        return name, np.asarray(machine.axes[letter].direction, float)
    return name, XYZ.index(name[1])


def _apply(where: np.ndarray | int, e_mm: np.ndarray) -> np.ndarray:
    out = np.zeros((e_mm.shape[0], 6))
    if isinstance(where, np.ndarray):
        out[:, :3] = e_mm[:, None] * where[None, :]
    else:
        out[:, where] = e_mm
    return out


def _positive(family: str, name: str, value: float) -> float:
    v = float(value)
    if not math.isfinite(v) or v <= 0:
        raise ValueError(f"{family}: {name} must be a positive number of mm, got {value!r}")
    return v


def cyclic_error(machine: Machine, axis: str | None, period_mm: float | None = None,
                 component: str | None = None) -> Effect:
    """A cyclic error of period ``period_mm`` along (or across) a linear axis; params
    ``<component>_cos`` and ``_sin`` in µm, phase 0 at controller position 0."""
    letter = need_axis(machine, "cyclic_error", axis, LINEAR_LETTERS)
    if period_mm is None:
        raise ValueError("cyclic_error: option period_mm is required (mm)")
    period = _positive("cyclic_error", "period_mm", period_mm)
    name, where = _component(machine, "cyclic_error", letter, component)
    sign = machine.axes[letter].sign

    def motion(p: np.ndarray) -> dict[str, MotionErrorFn]:
        def fn(q: np.ndarray) -> np.ndarray:
            w = 2.0 * np.pi * np.asarray(q, float) * sign / period  # controller position
            return _apply(where, (p[0] * np.cos(w) + p[1] * np.sin(w)) * UM)

        return {letter: fn}

    return Effect("cyclic_error", letter, (f"{name}_cos", f"{name}_sin"), ("um", "um"),
                  _motion=motion, note=f"cyclic {name}, period {period:g} mm; {OUTSIDE_NOTE}")


def local_bump(machine: Machine, axis: str | None, centre_mm: float | None = None,
               width_mm: float | None = None, component: str | None = None) -> Effect:
    """A raised-cosine bump of full width ``width_mm`` at controller position ``centre_mm``
    of a linear axis; param ``<component>_height`` in µm."""
    letter = need_axis(machine, "local_bump", axis, LINEAR_LETTERS)
    if centre_mm is None or width_mm is None:
        raise ValueError("local_bump: options centre_mm and width_mm are required (mm)")
    centre = float(centre_mm)
    if not math.isfinite(centre):
        raise ValueError(f"local_bump: centre_mm must be a number of mm, got {centre_mm!r}")
    width = _positive("local_bump", "width_mm", width_mm)
    name, where = _component(machine, "local_bump", letter, component)
    sign = machine.axes[letter].sign

    def motion(p: np.ndarray) -> dict[str, MotionErrorFn]:
        def fn(q: np.ndarray) -> np.ndarray:
            u = np.clip((np.asarray(q, float) * sign - centre) / (0.5 * width), -1.0, 1.0)
            return _apply(where, p[0] * 0.5 * (1.0 + np.cos(np.pi * u)) * UM)

        return {letter: fn}

    return Effect("local_bump", letter, (f"{name}_height",), ("um",), _motion=motion,
                  note=f"local {name} over {width:g} mm at {centre:g} mm; {OUTSIDE_NOTE}")
