"""Whether a plan's estimate poses can identify a rotary axis' positioning harmonics."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

# A validate pose whose prediction leverage for the harmonic exceeds this multiple of the
# largest on the estimate poses is an extrapolation: on annex B's roles 2C takes 0/60/300° on
# the estimate poses and 180° on a validate pose, leverage 7.0 against 0.5 (×14); the
# interleaved shift_holdout_14poses plan gives ×1.0 for orders 1-2 of B and C.
EXTRAPOLATION = 2.0
ORDERS = (1, 2)  # the library's rotary_positioning harmonics (identification.effects)
_ORDINAL = {1: "1st", 2: "2nd", 3: "3rd"}


@dataclass(frozen=True)
class HarmonicSupport:
    """One rotary axis' harmonic of one order on a plan's estimate (and validate) poses."""

    axis: str
    order: int
    distinct: int  # distinct values of order × angle (mod 360°) on the estimate poses
    rank: int  # rank of [1, cos kθ, sin kθ] on the estimate poses (3 = identifiable)
    leverage_estimate: float  # largest prediction leverage on an estimate pose
    leverage_validate: float  # the same on a validate pose (nan without validate poses)

    @property
    def ok(self) -> bool:
        return self.rank == 3 and not (self.leverage_validate
                                       > EXTRAPOLATION * self.leverage_estimate)

    @property
    def message(self) -> str:
        """Why the estimate poses cannot identify it ('' when they can)."""
        if self.ok:
            return ""
        what = f"{_ORDINAL.get(self.order, f'{self.order}th')} harmonic of {self.axis}"
        k = "" if self.order == 1 else str(self.order)
        head = (f"{what}: the estimate poses give {k}{self.axis} only {self.distinct} distinct "
                f"value{'s' if self.distinct != 1 else ''}")
        if self.rank < 3:
            return f"{head}; they cannot identify it (rank {self.rank} of 3)"
        return (f"{head}; the validate poses extrapolate it (prediction leverage "
                f"{self.leverage_validate:.2f} on a validate pose, at most "
                f"{self.leverage_estimate:.2f} on an estimate pose)")


def _rows(angles_deg: np.ndarray, order: int) -> np.ndarray:
    t = np.radians(angles_deg) * order
    return np.column_stack([np.ones_like(t), np.cos(t), np.sin(t)])


def harmonic_support(estimate_deg: Mapping[str, Sequence[float]],
                     validate_deg: Mapping[str, Sequence[float]] | None = None,
                     orders: Sequence[int] = ORDERS) -> list[HarmonicSupport]:
    """Per rotary axis (``{"C": [pose angles]}``, one angle per pose) and harmonic order: the
    design of a harmonic with a constant, ``[1, cos kθ, sin kθ]``, on the estimate poses and the
    leverage ``x'(X'X)⁺x`` it gives the validate poses (the constant stands for the links that
    absorb an order-0 term). A rank below 3 cannot identify the harmonic; a validate leverage
    above EXTRAPOLATION × the estimate poses' maximum extrapolates it there."""
    out = []
    for axis, est in estimate_deg.items():
        e = np.asarray(est, dtype=float)
        v = np.asarray((validate_deg or {}).get(axis, ()), dtype=float)
        for k in orders:
            x = _rows(e, k)
            gram = np.linalg.pinv(x.T @ x, rcond=1e-12)
            rank = int(np.linalg.matrix_rank(x, tol=1e-9))
            h_e = float(np.max(np.einsum("ij,jk,ik->i", x, gram, x))) if len(e) else 0.0
            xv = _rows(v, k)
            h_v = float(np.max(np.einsum("ij,jk,ik->i", xv, gram, xv))) if len(v) else np.nan
            distinct = len({round(a, 6) for a in np.mod(e * k, 360.0)})
            out.append(HarmonicSupport(axis, k, distinct, rank, h_e, h_v))
    return out


def warnings(estimate_deg: Mapping[str, Sequence[float]],
             validate_deg: Mapping[str, Sequence[float]] | None = None,
             orders: Sequence[int] = ORDERS) -> list[str]:
    """The messages of the harmonics the estimate poses cannot identify (empty when all can)."""
    return [s.message for s in harmonic_support(estimate_deg, validate_deg, orders) if not s.ok]
