"""The map's parameters: one Legendre coefficient per (linear axis, motion error, degree) over the
covered range of that axis, and the chain functions they make.

Coefficients are in mm (translations EXX … EZZ) or rad (rotations EAX … ECZ) inside, µm / µrad in
reports; the argument is the axis' model joint value (mm, the sign of the machine file applied,
``kinematics.to_model``). Degree 0 is never a term: a constant motion error is a setup offset
(a translation) or a location error, a zero offset of a following rotary axis or a rigid
rotation (a rotation): the setup and links of today's method hold it, and a map is defined up to
a rigid motion anyway (METHOD.md §7).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from identification.kinematics import MotionErrorFn
from identification.linmap.basis import (
    LINEAR,
    component_name,
    is_rotation,
    legendre_values,
    to_unit,
)


@dataclass(frozen=True, order=True)
class MapTerm:
    """Degree ``degree`` of motion error ``slot`` (0..5: EX, EY, EZ, EA, EB, EC) of ``axis``."""

    axis: str
    slot: int
    degree: int

    @property
    def component(self) -> str:
        return component_name(self.slot, self.axis)

    @property
    def name(self) -> str:
        return f"{self.component}_P{self.degree}"

    @property
    def rotation(self) -> bool:
        return is_rotation(self.slot)

    @property
    def unit(self) -> str:
        return "urad" if self.rotation else "um"

    @property
    def to_si(self) -> float:
        """Internal unit (mm or rad) → report unit (µm or µrad)."""
        return 1e6 if self.rotation else 1e3


def candidate_terms(axes: Sequence[str], max_degree: int) -> list[MapTerm]:
    """Every term up to ``max_degree`` in the order the observability test keeps them: by degree,
    then translations before rotations (with one stylus length an angular error and a
    straightness move the tip alike: the straightness is kept and holds their sum), positioning
    first among the translations, axes X, Y, Z (without a calibrated distance the isotropic
    scale drops the last positioning slope, EZZ_P1)."""
    out = []
    for k in range(1, max_degree + 1):
        for group in ("positioning", "straightness", "rotation"):
            for axis in axes:
                i = LINEAR.index(axis)
                slots = {"positioning": [i], "straightness": [s for s in range(3) if s != i],
                         "rotation": [3, 4, 5]}[group]
                out += [MapTerm(axis, s, k) for s in slots]
    return out


@dataclass(frozen=True)
class MapBasis:
    """The terms of a map and the interval each axis' Legendre polynomials span (model joint
    values, mm): the covered range of that axis."""

    ranges_mm: Mapping[str, tuple[float, float]]
    terms: tuple[MapTerm, ...]

    def __post_init__(self) -> None:
        for t in self.terms:
            lo, hi = self.ranges_mm[t.axis]
            if not hi > lo:
                raise ValueError(f"axis {t.axis}: covered range [{lo}, {hi}] mm is empty")

    @property
    def size(self) -> int:
        return len(self.terms)

    @property
    def names(self) -> list[str]:
        return [t.name for t in self.terms]

    def subset(self, keep: Sequence[int]) -> MapBasis:
        return MapBasis(self.ranges_mm, tuple(self.terms[i] for i in keep))

    def axis_terms(self, axis: str) -> list[int]:
        return [i for i, t in enumerate(self.terms) if t.axis == axis]

    def values(self, axis: str, q_mm: np.ndarray) -> np.ndarray:
        """(N, n) P_k(u(q)) of the terms of ``axis`` (in ``axis_terms`` order), no extension:
        the fit evaluates inside the covered range (and 1 mm around it for derivatives)."""
        idx = self.axis_terms(axis)
        lo, hi = self.ranges_mm[axis]
        u = to_unit(q_mm, lo, hi)
        if not idx:
            return np.zeros((np.shape(u)[0], 0))
        deg = sorted({self.terms[i].degree for i in idx})
        v = legendre_values(u, deg)
        col = {d: j for j, d in enumerate(deg)}
        return v[:, [col[self.terms[i].degree] for i in idx]]

    def motion_errors(self, coef: np.ndarray) -> dict[str, MotionErrorFn]:
        """The chain functions (kinematics.ChainState.motion_errors) for coefficients ``coef``
        (mm / rad, one per term)."""
        c = np.asarray(coef, float).reshape(-1)
        if c.shape[0] != self.size:
            raise ValueError(f"expected {self.size} map coefficients, got {c.shape[0]}")
        out: dict[str, MotionErrorFn] = {}
        for axis in LINEAR:
            idx = self.axis_terms(axis)
            if not idx or not np.any(c[idx]):
                continue
            slots = np.array([self.terms[i].slot for i in idx])
            ca = c[idx]

            def fn(q: np.ndarray, axis: str = axis, slots: np.ndarray = slots,
                   ca: np.ndarray = ca) -> np.ndarray:
                v = self.values(axis, np.asarray(q, float).reshape(-1)) * ca
                e = np.zeros((v.shape[0], 6))
                np.add.at(e.T, slots, v.T)
                return e

            out[axis] = fn
        return out
