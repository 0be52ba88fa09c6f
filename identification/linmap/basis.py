"""Smooth functions of a linear axis' position: Legendre polynomials over an interval, the ISO
230-1 names of the six motion errors of an axis, and a smooth random draw of such functions.

A motion error of axis L (seed 003 §2, ISO 230-1: EXL, EYL, EZL, EAL, EBL, ECL) is written
e(x) = Σ_k a_k P_k(u), u = (2x − lo − hi)/(hi − lo) mapping the interval [lo, hi] onto [−1, 1]
(seed 004 Eqs (4)-(6) fit parametric errors as polynomials in the position; Legendre polynomials
are the same space, orthogonal over the interval, so coefficients of different degrees are
nearly uncorrelated and each says how much of the function that degree carries).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.polynomial import legendre as leg

SLOTS = "XYZABC"  # [EX, EY, EZ, EA, EB, EC]: the order of kinematics.MotionErrorFn's columns
LINEAR = "XYZ"


def component_name(slot: int, axis: str) -> str:
    """ISO 230-1 name of motion error ``slot`` (0..5) of linear axis ``axis``: EXX … ECZ."""
    return f"E{SLOTS[slot]}{axis}"


def component_names(axis: str) -> tuple[str, ...]:
    """The six motion errors of ``axis`` in slot order (EXX, EYX, EZX, EAX, EBX, ECX for X)."""
    return tuple(component_name(s, axis) for s in range(6))


def is_rotation(slot: int) -> bool:
    return slot >= 3


def to_unit(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """u = (2x − lo − hi)/(hi − lo): the interval [lo, hi] → [−1, 1]."""
    return (2.0 * np.asarray(x, float) - lo - hi) / (hi - lo)


def legendre_values(u: np.ndarray, degrees: Sequence[int]) -> np.ndarray:
    """(N, len(degrees)) values of P_k(u) for k in ``degrees``."""
    u = np.asarray(u, float).reshape(-1)
    if not len(degrees):
        return np.zeros((u.shape[0], 0))
    v = leg.legvander(u, int(max(degrees)))
    return v[:, list(degrees)]


def legendre_function(coef: Sequence[float], x: np.ndarray, lo: float, hi: float,
                      extend: bool = True) -> np.ndarray:
    """Σ_k coef[k] P_k(u(x)) (coef[0] the constant). ``extend``: beyond [lo, hi] the function
    continues as the straight line tangent at the nearer end (a polynomial would run away:
    P4(2) = 55), so a simulated machine stays smooth and bounded over its whole travel."""
    c = np.asarray(coef, float)
    u = to_unit(x, lo, hi)
    if not extend:
        return leg.legval(u, c)
    uc = np.clip(u, -1.0, 1.0)
    dc = leg.legder(c) if len(c) > 1 else np.zeros(1)
    return leg.legval(uc, c) + leg.legval(uc, dc) * (u - uc)


@dataclass(frozen=True)
class SmoothDraw:
    """Amplitudes of a random smooth machine: each motion error's max |e| over its interval is
    drawn uniformly in ``translation_um`` (µm) or ``rotation_urad`` (µrad)."""

    translation_um: tuple[float, float]
    rotation_urad: tuple[float, float]
    order: int = 4


def random_smooth(rng: np.random.Generator, draw: SmoothDraw, slot: int) -> np.ndarray:
    """Legendre coefficients (P0..P_order, µm or µrad) of one random smooth motion error: degree
    k's coefficient ~ N(0, 1/k²) (a spectrum falling with degree: a smooth, not a wavy, error),
    no constant (a constant is a setup offset or a link), scaled so that max |e| over the
    interval equals an amplitude drawn uniformly in the range of its kind."""
    k = np.arange(1, draw.order + 1)
    c = np.concatenate([[0.0], rng.normal(0.0, 1.0, draw.order) / k])
    lo, hi = draw.rotation_urad if is_rotation(slot) else draw.translation_um
    amp = rng.uniform(lo, hi)
    peak = float(np.max(np.abs(leg.legval(np.linspace(-1.0, 1.0, 401), c))))
    return c * (amp / peak) if peak > 0 else c
