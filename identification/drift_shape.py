"""A TCP drift's time course and its columns in the drift-aware fit: the model (shape,
axes, τ), the touches a centre was fitted from, and the shape normalised over the run."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from identification.model import Centres

SHAPES = ("linear", "exponential")


@dataclass(frozen=True)
class DriftModel:
    """Which drift: shape, drifting controller axes and (exponential) time constant."""

    shape: str
    axes: tuple[str, ...]
    tau_s: float | None = None

    def columns(self, t_s: np.ndarray, touch: Touches | None = None) -> np.ndarray:
        """(K, 3, m) change of the centres (mm) per µm of drift over the run, per axis: the
        drift at each centre's time, or with ``touch`` (centres fitted from touches) the
        drift at each touch's time carried through the sphere fit, Σ_i S_i δ(t_i)."""
        t = np.asarray(t_s, float)
        out = np.zeros((len(t), 3, len(self.axes)))
        if touch is None:
            f = shape_values(self.shape, t, self.tau_s)
            for j, a in enumerate(self.axes):
                out[:, "XYZ".index(a), j] = f * 1e-3
            return out
        t0, span = float(t.min()), float(t.max() - t.min())
        f = shape_values(self.shape, touch.t_s, self.tau_s, t0, span)  # (K, n)
        for j, a in enumerate(self.axes):
            out[:, :, j] = np.einsum("knc,kn->kc", touch.sens[:, :, :, "XYZ".index(a)], f) * 1e-3
        return out


@dataclass(frozen=True)
class Touches:
    """The touches behind centres fitted by ``rows_to_centres``: time (K, n) and the fit's
    ∂centre/∂point (K, n, 3, 3) (``Centres.touch_t_s``, ``touch_sens``)."""

    t_s: np.ndarray
    sens: np.ndarray

    @classmethod
    def of(cls, centres: Centres) -> Touches | None:
        """None for centres without their touches (an instrument's, a CMM's)."""
        ok = len(centres) > 0 and len(centres.touch_t_s) == len(centres) and np.all(
            np.isfinite(centres.touch_t_s))
        return cls(centres.touch_t_s, centres.touch_sens) if ok else None


def shape_values(shape: str, t_s: np.ndarray, tau_s: float | None, t0_s: float | None = None,
                 span_s: float | None = None) -> np.ndarray:
    """f(t) / f(T): the drift's time course from ``t0_s`` normalised to 1 at its end
    ``t0_s + span_s`` (default: the first and the last of ``t_s``)."""
    t = np.asarray(t_s, float) - (float(np.min(t_s)) if t0_s is None else t0_s)
    span = float(t.max()) if span_s is None else span_s
    if shape == "linear":
        return t / span
    if shape == "exponential" and tau_s:
        return -np.expm1(-t / tau_s) / -math.expm1(-span / tau_s)
    raise ValueError(f"drift shape must be one of {SHAPES} (exponential with tau_s)")
