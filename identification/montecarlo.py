"""Monte Carlo uncertainty of the setup estimates in the thesis Table 4.1 set-up (§4.3.1).

Link errors are drawn N(0, 5 µrad / 5 µm); the centres they produce are fitted with the setup
errors alone or together with the link errors; the spread of the setup estimates over the
draws is the uncertainty "due to the identification method". Around the nominal chain the
estimator is linear (errors of 5 µrad change the Jacobian by ~1e-5 relative, see
tests/test_montecarlo.py for the check against exact-chain re-estimation), so a draw is
``data = J_links · e`` and its estimate ``pinv(J_est) · data``; the product
``M = pinv(J_est) · J_links`` is formed once and every draw costs one small matrix product.
The probing-repeatability contribution is propagated exactly: pinv · Σ · pinvᵀ.

Aggregates: ``artefact_um`` = RMS over every ball coordinate of the per-coordinate standard
uncertainty; ``probe_um`` = the same over the three probe coordinates (per-coordinate values
are returned too).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from identification.identifiability import nominal_centres
from identification.kinematics import Machine
from identification.model import Artefact, Layout, predict

THESIS_REPEATABILITY_UM = (0.66, 0.98, 0.44)  # thesis §3.4, centre std x, y, z


@dataclass(frozen=True)
class MonteCarlo:
    """Standard uncertainties (µm) of the setup estimates."""

    simultaneous: bool
    draws: int
    balls_um: np.ndarray  # (n, 3) method contribution, per coordinate (Monte Carlo)
    probe_um: np.ndarray  # (3,)
    balls_repeat_um: np.ndarray  # (n, 3) probing-repeatability contribution (exact)
    probe_repeat_um: np.ndarray  # (3,)
    links_repeat: np.ndarray | None  # (L,) link std from repeatability (µrad / µm)

    @staticmethod
    def _rms(a: np.ndarray) -> float:
        return float(np.sqrt(np.mean(np.asarray(a) ** 2)))

    @property
    def artefact_um(self) -> float:
        return self._rms(self.balls_um)

    @property
    def probe_agg_um(self) -> float:
        return self._rms(self.probe_um)

    @property
    def artefact_repeat_um(self) -> float:
        return self._rms(self.balls_repeat_um)

    @property
    def probe_repeat_agg_um(self) -> float:
        return self._rms(self.probe_repeat_um)


def grid_poses(b_range_deg: tuple[float, float] = (-45.0, 45.0), c_range_deg: tuple[float, float]
               = (0.0, 360.0), step_deg: float = 15.0) -> list[tuple[float, float]]:
    """Table 4.1 grid: B and C over their ranges (ends included) in ``step_deg`` steps."""
    bs = np.arange(b_range_deg[0], b_range_deg[1] + 1e-9, step_deg)
    cs = np.arange(c_range_deg[0], c_range_deg[1] + 1e-9, step_deg)
    return [(float(b), float(c)) for b in bs for c in cs]


def jacobian(machine: Machine, artefact: Artefact, poses: Sequence[tuple[float, float]],
             links: Sequence[str]) -> tuple[np.ndarray, Layout]:
    """Jacobian (3mn, P) of the nominal centres for the layout (links, setup)."""
    centres = nominal_centres(machine, artefact, list(poses))
    layout = Layout(tuple(links), len(artefact.balls))
    _, jac = predict(machine, artefact, layout, np.zeros(layout.size), centres, jacobian=True)
    return jac.reshape(-1, layout.size), layout


def linear_estimator(jac: np.ndarray, layout: Layout, simultaneous: bool
                     ) -> tuple[np.ndarray, np.ndarray]:
    """(pinv of the estimated columns, indices of those columns in ``layout``)."""
    nl = len(layout.links)
    cols = np.arange(layout.size) if simultaneous else np.arange(nl, layout.size)
    return np.linalg.pinv(jac[:, cols]), cols


def run(machine: Machine, artefact: Artefact, poses: Sequence[tuple[float, float]],
        links: Sequence[str], simultaneous: bool, draws: int = 10_000,
        sigma_urad: float = 5.0, sigma_um: float = 5.0,
        repeatability_um: Sequence[float] = THESIS_REPEATABILITY_UM, seed: int = 0,
        jac: np.ndarray | None = None) -> MonteCarlo:
    """Draw link errors, estimate, return the spread of the setup estimates (Table 4.1)."""
    if jac is None:
        jac, layout = jacobian(machine, artefact, poses, links)
    else:
        layout = Layout(tuple(links), len(artefact.balls))
    nl = len(links)
    pinv, cols = linear_estimator(jac, layout, simultaneous)
    sig = np.array([sigma_urad * 1e-6 if n[1] in "ABC" else sigma_um * 1e-3 for n in links])
    rng = np.random.default_rng(seed)
    e = rng.standard_normal((draws, nl)) * sig  # (D, L) mm / rad
    m = pinv @ jac[:, :nl]  # (P_est, L): estimate per unit link error
    est = e @ m.T  # (D, P_est)
    # True setup errors are zero in the linear model, so the estimates are the errors.
    setup_pos = np.flatnonzero(cols >= nl)
    setup = est[:, setup_pos]
    std = setup.std(axis=0) * 1e3
    n = layout.n_balls
    # Repeatability: cov = pinv Σ pinvᵀ with Σ = diag(σx², σy², σz²) per centre.
    rep = np.tile(np.asarray(repeatability_um, float) * 1e-3, jac.shape[0] // 3)
    pw = pinv * rep[None, :]
    rep_std = np.sqrt(np.einsum("ij,ij->i", pw, pw))
    rep_setup = rep_std[setup_pos] * 1e3
    links_rep = None
    if simultaneous:
        links_rep = np.array([rep_std[i] * (1e6 if links[i][1] in "ABC" else 1e3)
                              for i in range(nl)])
    return MonteCarlo(simultaneous, draws, std[: 3 * n].reshape(n, 3), std[3 * n:],
                      rep_setup[: 3 * n].reshape(n, 3), rep_setup[3 * n:], links_rep)
