"""What a plan's timing lets the estimator say about a warm-up: per axis and shape,
whether a TCP drift separates from the links (``identification.drift.separation``), the
predicted uncertainty of the drift over the run and what estimating it costs the links.

Every ball of a visit is given the visit's time (the plan knows visits, not touches): the
within-visit spread in time, which helps a little, is left out, so the answer is conservative.
With a stated rotary repeatability the covariances are the estimator's visit sandwich under it
(``programs.design``): a visit's index error moves its balls together, as a drift step would.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from contracts.setup_files import Plan
from identification.drift import SEPARABLE_MIN, DriftModel, separation
from identification.identifiability import nominal_centres
from identification.kinematics import Machine
from identification.model import Artefact, Centres, Layout, predict
from programs.design import H_DEG

TAU_S = 900.0  # a typical warm-up time constant (ISO 230-3: 10-60 min on a machining centre)


@dataclass(frozen=True)
class DriftPlan:
    """Per shape (linear, exponential at ``TAU_S``): separable fraction and u of the drift over
    the run (µm) per axis X Y Z, and the largest link-u growth when all three are estimated."""

    separation: dict[str, tuple[float, float, float]]
    over_run_u_um: dict[str, tuple[float, float, float]]
    link_growth: dict[str, float]
    span_s: float
    # τ itself: per axis, the separable fraction of the warm-up's bend (its derivative by ln τ,
    # with the links, setup and the warm-ups fitted) and the drift over the run (µm) from
    # which τ is known to ±50 % (u(ln τ) = 0.5); inf where the plan cannot see the bend
    tau_separation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    tau_from_um: tuple[float, float, float] = (float("inf"),) * 3

    def inseparable(self) -> list[str]:
        """"<shape> <axis>" the plan cannot separate from the links."""
        return [f"{shape} {a}" for shape, sep in self.separation.items()
                for a, s in zip("XYZ", sep, strict=True) if s < SEPARABLE_MIN]

    def lines(self, name: str) -> list[str]:
        """What ``rumba plan`` prints about it."""
        out = []
        for shape in self.separation:
            u = self.over_run_u_um[shape]
            what = "linear drift" if shape == "linear" else f"warm-up (τ {TAU_S / 60:.0f} min)"
            out.append(f"{name}: {what} over the run ({self.span_s / 60:.1f} min) separable "
                       f"from the links, u X/Y/Z {'/'.join(f'{x:.2g}' for x in u)} µm; link u "
                       f"grows at most ×{self.link_growth[shape]:.2f} when it is estimated")
        if "exponential" in self.separation and np.isfinite(min(self.tau_from_um)):
            dull = [a for a, x in zip("XYZ", self.tau_separation, strict=True)
                    if x < SEPARABLE_MIN]
            out.append(f"{name}: τ ({TAU_S / 60:.0f} min) known to ±50 % only from a warm-up "
                       f"of ≥ {'/'.join(f'{x:.2g}' for x in self.tau_from_um)} µm (X/Y/Z) over "
                       "the run; below that the drift over the run is fitted with τ at a "
                       "bound (a straight line when τ ≫ the run)"
                       + (f"; the plan cannot tell the warm-up's bend from the links on "
                          f"{'/'.join(dull)}" if dull else ""))
        bad = self.inseparable()
        if bad:
            out = [f"{name}: the plan cannot separate drift from links: {', '.join(bad)} "
                   "(add a revisit of a pose later in the run, or interleave the order)"]
        return out


def drift_plan(machine: Machine, artefact: Artefact, visits: Sequence[tuple[float, float]],
               times_s: Sequence[float], links: Sequence[str], sigma_um: Sequence[float],
               index_urad: Mapping[str, float] | None = None) -> DriftPlan:
    """The drift ``visits`` (estimate visits in run order, each at ``times_s``) can resolve;
    ``index_urad``: the machine file's stated rotary repeatability (µrad 1σ by axis letter)."""
    n = len(artefact.balls)
    c = nominal_centres(machine, artefact, list(visits))
    layout = Layout(tuple(links), n, scale=bool(artefact.distances))
    pred, j = predict(machine, artefact, layout, np.zeros(layout.size), c, jacobian=True)
    zs = _index_columns(machine, artefact, layout, c, pred, index_urad)
    t = np.repeat(np.asarray(times_s, float), n)
    sig = np.asarray(sigma_um, float) * 1e-3
    nl = len(links)
    span = float(t.max() - t.min()) if t.size else 0.0
    if span <= 0.0:  # no time between the visits: a drift is one more relocalisation
        zero = (0.0, 0.0, 0.0)
        inf = (float("inf"),) * 3
        return DriftPlan({"linear": zero, "exponential": zero},
                         {"linear": inf, "exponential": inf},
                         {"linear": float("inf"), "exponential": float("inf")}, 0.0)
    seps, us, growth = {}, {}, {}
    base = _cov(j, np.zeros((len(t), 3, 0)), sig, zs, n)
    for shape in ("linear", "exponential"):
        cols = DriftModel(shape, ("X", "Y", "Z"), TAU_S if shape == "exponential"
                          else None).columns(t)
        seps[shape] = tuple(float(x) for x in separation(j, sig, cols))
        cov = _cov(j, cols, sig, zs, n)
        us[shape] = tuple(float(np.sqrt(cov[layout.size + k, layout.size + k]))
                          for k in range(3))
        g = np.sqrt(np.diag(cov)[:nl] / np.maximum(np.diag(base)[:nl], 1e-300))
        growth[shape] = float(g.max()) if nl else 1.0
    tau_sep, tau_from = _tau(j, t, sig, layout.size, zs, n)
    return DriftPlan(seps, us, growth, span, tau_sep, tau_from)


def _index_columns(machine: Machine, artefact: Artefact, layout: Layout, c: Centres,
                   pred: np.ndarray, index_urad: Mapping[str, float] | None
                   ) -> np.ndarray | None:
    """(K, 3, q) each centre moved by a stated 1σ index error of each rotary axis (mm);
    None when nothing is stated (the covariances as before, bit for bit)."""
    stated = [float((index_urad or {}).get(a, 0.0)) for a in machine.rotary_axes[:2]]
    if not any(v > 0 for v in stated):
        return None
    zs = np.zeros((len(c), 3, len(stated)))
    for k, s_urad in enumerate(stated):
        moved = Centres(c.pose, c.ball, c.b_deg + (H_DEG if k == 0 else 0.0),
                        c.c_deg + (H_DEG if k == 1 else 0.0), c.xyz_mm, c.t_s)
        q1, _ = predict(machine, artefact, layout, np.zeros(layout.size), moved)
        zs[:, :, k] = (q1 - pred) / np.deg2rad(H_DEG) * s_urad * 1e-6
    return zs


def _tau(j: np.ndarray, t: np.ndarray, sig: np.ndarray, n_par: int,
         zs: np.ndarray | None = None, n: int = 1
         ) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """(separable fraction of each axis' warm-up bend, drift over the run from which τ is known
    to ±50 %): the derivative of the normalised warm-up by ln τ per axis, beside the links, the
    setup and the warm-ups themselves (identification/drift.py fits τ so, to first order)."""
    model = DriftModel("exponential", ("X", "Y", "Z"), TAU_S)
    cols = model.columns(t)
    h = 1e-4
    dcol = (DriftModel("exponential", model.axes, TAU_S * np.exp(h)).columns(t)
            - DriftModel("exponential", model.axes, TAU_S * np.exp(-h)).columns(t)) / (2 * h)
    sep = separation(np.concatenate([j, cols], axis=2), sig, dcol)
    cov = _cov(np.concatenate([j, cols], axis=2), dcol, sig, zs, n)
    # coefficient of dcol = A·d(ln τ) with A the drift over the run in µm: u(ln τ) = u(c) / A
    u_c = np.sqrt(np.diag(cov)[n_par + 3:])
    tau_from = tuple(float(2.0 * u) if s >= SEPARABLE_MIN else float("inf")
                     for u, s in zip(u_c, sep, strict=True))
    return tuple(float(x) for x in sep), tau_from


def _cov(j: np.ndarray, cols: np.ndarray, sig: np.ndarray, zs: np.ndarray | None = None,
         n: int = 1) -> np.ndarray:
    """(JᵀWJ)⁻¹ of the links, setup and drift (pseudo-inverse: an inseparable drift gives
    huge, not infinite, numbers); with index columns ``zs`` (K, 3, q; the centres of a visit
    are ``n`` consecutive rows) the visit sandwich A⁻¹ (A + Σ_v h_v h_vᵀ) A⁻¹."""
    a = np.concatenate([j, cols], axis=2)
    w = (a / sig[None, :, None]).reshape(-1, a.shape[2])
    norms = np.linalg.norm(w, axis=0)
    norms[norms == 0] = 1.0
    if zs is None:
        return np.linalg.pinv((w / norms).T @ (w / norms)) / np.outer(norms, norms)
    wn = w / norms
    a_inv = np.linalg.pinv(wn.T @ wn)
    v = len(zs) // n
    h = np.einsum("vrp,vra->vpa", wn.reshape(v, 3 * n, -1),
                  (zs / sig[None, :, None]).reshape(v, 3 * n, -1))
    meat = wn.T @ wn + np.einsum("vpa,vqa->pq", h, h)
    return a_inv @ meat @ a_inv / np.outer(norms, norms)


def plan_times_s(plan: Plan, total_s: float) -> list[float]:
    """Mid times of the estimate visits of ``plan`` when its ``total_s`` seconds are spread
    evenly over all its visits (validation poses and the revisit included)."""
    order = [(p.b_deg, p.c_deg, p.role) for p in plan.poses] * plan.repeats
    if plan.drift_check:
        p0 = plan.poses[0]
        order.append((p0.b_deg, p0.c_deg, p0.role))
    step = total_s / len(order)
    return [(i + 0.5) * step for i, v in enumerate(order) if v[2] == "estimate"]


__all__ = ["TAU_S", "DriftPlan", "drift_plan", "plan_times_s"]
