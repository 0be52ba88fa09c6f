"""What a pose set buys: the predicted standard uncertainty of every link from the identification
Jacobian, per pose, before anything is probed (optimal design, Atkinson, Donev & Tobias 2007).

The estimator (``identification.estimate``) fits links and setup errors to the measured centres
by weighted least squares; with the centre repeatability σ given per controller axis its
covariance is ``(JᵀWJ)⁻¹``, W = diag(σ⁻²) (thesis eqs 4.1-4.2; the calibrated distances of a
scale-enriched artefact add their rows). J is linear in the poses: the information matrix of a
plan is the sum of one block per visit, ``I_p = J_pᵀ W J_p`` (every ball of pose p), evaluated
at the nominal machine (5 µrad errors change J by ~1e-5 relative: identification/montecarlo.py).
So a candidate grid is differentiated once and every plan is a sum of blocks.

Index scatter: with a stated rotary repeatability (machine file
``rotary_repeatability_urad``, µrad 1σ per indexation) every ball of a visit moves with that
visit's index error, so the centres of one visit are correlated and the estimator reports the
visit sandwich A⁻¹ (Σ_v J_vᵀ W V_v W J_v) A⁻¹ (``identification.estimate_scatter``), here with
V_v = W⁻¹ + Σ_a σ_a² z_va z_vaᵀ (z_va: the visit's centres moved per radian of axis a): the
meat is A + Σ_v Σ_a h_va h_vaᵀ, h_va = J_vᵀ W z_va σ_a, again one block per candidate. A
revisit or another indexation averages the index error out; another ball of the same visit
does not. Nothing stated: no such block, the covariance is A⁻¹ exactly as before.

Drift: a thermal drift of the measured centres per controller axis — linear (three rates, the
gap diagnosis' ``thermal_drift`` family) or a warm-up A·(1 − e^(−t/τ)) with τ estimated (issue
22) — added as nuisance columns, with each visit at its time in the plan, gives the uncertainty
the links keep when drift must be told apart from pose effects: a plan whose time order follows
C (or B) confounds the two and inflates it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from identification.identifiability import identifiable_links, nominal_centres
from identification.kinematics import Machine
from identification.model import Artefact, Centres, Layout, predict

H_DEG = 1e-3  # the index columns' finite-difference step (as identification.estimate_scatter)


@dataclass(frozen=True)
class Design:
    """Information blocks of candidate poses for one layout (links + setup [+ scale])."""

    links: tuple[str, ...]
    layout: Layout
    poses: list[tuple[float, float]]
    jw: np.ndarray  # (N, 3n, P) Jacobian of each pose's centres, rows weighted by 1/σ
    info: np.ndarray  # (N, P, P) J_pᵀ W J_p
    prior: np.ndarray  # (P, P) information of the calibrated distances (0 without)
    unit: np.ndarray  # (L,) rad → µrad, mm → µm
    sigma_um: np.ndarray  # (3,)
    centres_mm: np.ndarray  # (N, n, 3) nominal ball centres, controller X Y Z, per pose
    # (N, 3n, q) each candidate's centres moved by a stated 1σ index error of each rotary
    # axis, rows weighted by 1/σ; None: nothing stated (exact indexing assumed)
    zw: np.ndarray | None = None
    index_info: np.ndarray | None = None  # (N, P, P) Σ_a h_a h_aᵀ, h_a = J_pᵀ W z_a σ_a
    index_urad: tuple[tuple[str, float], ...] = ()  # the stated values, by axis letter

    def info_of(self, counts: np.ndarray) -> np.ndarray:
        """Information of a plan visiting candidate k ``counts[k]`` times."""
        return self.prior + np.einsum("k,kij->ij", np.asarray(counts, float), self.info)

    def meat_of(self, counts: np.ndarray) -> np.ndarray | None:
        """The index scatter's share of the sandwich's meat for those counts (each visit an
        indexation of its own); None without a stated repeatability."""
        if self.index_info is None:
            return None
        return np.einsum("k,kij->ij", np.asarray(counts, float), self.index_info)


def link_units(links: Sequence[str]) -> np.ndarray:
    """Report units per link: µrad for rotations (E[ABC]…), µm for translations."""
    return np.array([1e6 if n[1] in "ABC" else 1e3 for n in links])


def build_design(machine: Machine, artefact: Artefact, poses: Sequence[tuple[float, float]],
                 links: Sequence[str], sigma_um: Sequence[float],
                 index_urad: Mapping[str, float] | None = None) -> Design:
    """Differentiate the nominal centres of every candidate pose once; with ``index_urad``
    (stated rotary repeatability, µrad 1σ by axis letter) also along each rotary axis."""
    poses = [(float(b), float(c)) for b, c in poses]
    centres = nominal_centres(machine, artefact, poses)
    layout = Layout(tuple(links), len(artefact.balls), scale=bool(artefact.distances))
    pred, jac = predict(machine, artefact, layout, np.zeros(layout.size), centres,
                        jacobian=True)
    sig = np.asarray(sigma_um, float) * 1e-3
    n = len(artefact.balls)
    jw = (jac / sig[None, :, None]).reshape(len(poses), 3 * n, layout.size)
    info = np.einsum("kri,krj->kij", jw, jw)
    prior = np.zeros((layout.size, layout.size))
    ids = artefact.ids
    for cd in artefact.distances:  # as identification.estimate: rows on the ball offsets
        a, b = ids.index(cd.ball_a), ids.index(cd.ball_b)
        v = artefact.nominal_mm[a] - artefact.nominal_mm[b]
        row = np.zeros(layout.size)
        s = layout.ball_slice.start
        row[s + 3 * a:s + 3 * a + 3] = v / np.linalg.norm(v)
        row[s + 3 * b:s + 3 * b + 3] = -v / np.linalg.norm(v)
        row /= cd.std_um * 1e-3
        prior += np.outer(row, row)
    stated = [(a, float((index_urad or {}).get(a, 0.0))) for a in machine.rotary_axes[:2]]
    if not any(v > 0 for _, v in stated):  # nothing stated: today's design, bit for bit
        return Design(tuple(links), layout, poses, jw, info, prior, link_units(links),
                      np.asarray(sigma_um, float), centres.xyz_mm.reshape(len(poses), n, 3))
    zw = np.zeros((len(poses), 3 * n, len(stated)))
    for k, (_, s_urad) in enumerate(stated):
        moved = Centres(centres.pose, centres.ball, centres.b_deg + (H_DEG if k == 0 else 0.0),
                        centres.c_deg + (H_DEG if k == 1 else 0.0), centres.xyz_mm,
                        centres.t_s)
        q1, _ = predict(machine, artefact, layout, np.zeros(layout.size), moved)
        dz = (q1 - pred) / np.deg2rad(H_DEG) * s_urad * 1e-6 / sig[None, :]  # mm/rad·rad/mm
        zw[:, :, k] = dz.reshape(len(poses), 3 * n)
    h = np.einsum("kri,kra->kia", jw, zw)
    return Design(tuple(links), layout, poses, jw, info, prior, link_units(links),
                  np.asarray(sigma_um, float), centres.xyz_mm.reshape(len(poses), n, 3),
                  zw, np.einsum("kia,kja->kij", h, h), tuple(stated))


def link_u(design: Design, m: np.ndarray, extra: np.ndarray | None = None) -> np.ndarray:
    """Standard uncertainty per link (µrad / µm) from information matrices m (…, P, P); inf
    where m is singular (the plan cannot separate every parameter). ``extra`` (…, P, P): the
    index scatter's share of the meat (``Design.meat_of``), the covariance then the sandwich
    m⁻¹ (m + extra) m⁻¹."""
    m = np.asarray(m, float)
    scale = np.sqrt(np.maximum(np.einsum("...ii->...i", m), 1e-300))
    mn = m / (scale[..., :, None] * scale[..., None, :])  # unit diagonal: a fair rank test
    w, v = np.linalg.eigh(mn)
    ok = w[..., 0] > 1e-10 * w[..., -1]
    inv = np.einsum("...ik,...k,...jk->...ij", v, 1.0 / np.where(ok[..., None], w, 1.0), v)
    if extra is not None:
        en = extra / (scale[..., :, None] * scale[..., None, :])
        inv = inv + inv @ en @ inv
    var = np.einsum("...ii->...i", inv)[..., :len(design.links)] / \
        scale[..., :len(design.links)] ** 2
    u = np.sqrt(np.maximum(var, 0.0)) * design.unit
    return np.where(ok[..., None], u, np.inf)


def link_u_regular(design: Design, m: np.ndarray, extra: np.ndarray | None = None
                   ) -> np.ndarray:
    """``link_u`` for information matrices known to be regular (a ridge added): one LU solve
    for the link columns only, several times faster on a batch of candidates."""
    m = np.asarray(m, float)
    n_l = len(design.links)
    scale = np.sqrt(np.einsum("...ii->...i", m))
    mn = m / (scale[..., :, None] * scale[..., None, :])
    rhs = np.broadcast_to(np.eye(m.shape[-1])[:, :n_l], (*m.shape[:-2], m.shape[-1], n_l))
    x = np.linalg.solve(mn, rhs)
    var = np.einsum("...ii->...i", x[..., :n_l, :])
    if extra is not None:  # the sandwich's index share: xᵢᵀ extra xᵢ per link column
        en = extra / (scale[..., :, None] * scale[..., None, :])
        var = var + np.einsum("...pi,...pq,...qi->...i", x, en, x)
    var = var / scale[..., :n_l] ** 2
    return np.sqrt(np.maximum(var, 0.0)) * design.unit


WARMUP_TAU_H = (10 / 60, 30 / 60, 1.0)  # warm-up time constants searched (ISO 230-3: 10-60 min)


def drift_columns(times_h: Sequence[float], tau_h: float | None = None) -> np.ndarray:
    """(V, m) time functions of a drift per visit: a linear drift [t]; a warm-up
    [1 − e^(−t/τ), (t/τ)·e^(−t/τ)] — its shape and its derivative by ln τ, so that τ, which
    the estimator profiles (identification/drift.py), costs the links what it costs there
    (over a run much shorter than τ the pair spans t and t²: a drift that bends)."""
    t = np.asarray(times_h, float)
    if tau_h is None:
        return t[:, None]
    x = t / tau_h
    return np.column_stack([-np.expm1(-x), x * np.exp(-x)])


def drift_u(design: Design, visits: Sequence[int], times_h: Sequence[float],
            tau_h: float | None = None) -> np.ndarray:
    """Link uncertainty (µrad / µm) of the visits (candidate indices in run order, a repeat
    allowed) with a drift of the centres per controller axis estimated alongside: linear
    (three rates), or with ``tau_h`` a warm-up with its time constant (``drift_columns``)."""
    p = design.layout.size
    n3 = design.jw.shape[1]
    sig_mm = design.sigma_um[np.arange(n3) % 3] * 1e-3  # row r is axis r % 3 of its ball
    axis = np.tile(np.eye(3), (n3 // 3, 1)) / sig_mm[:, None]
    g = drift_columns(times_h, tau_h)
    blocks = [np.hstack([design.jw[k], np.kron(g[i][None, :], axis)])
              for i, k in enumerate(visits)]
    j = np.vstack(blocks)
    m = j.T @ j
    m[:p, :p] += design.prior
    if design.zw is None:
        return link_u(design, m)
    # each visit's index error moves its balls together: the drift columns see it too
    h = [b.T @ design.zw[k] for b, k in zip(blocks, visits, strict=True)]
    return link_u(design, m, sum(x @ x.T for x in h))


def drift_u_worst(design: Design, visits: Sequence[int], times_h: Sequence[float]
                  ) -> np.ndarray:
    """Per link, the largest ``drift_u`` of a linear drift and of a warm-up with τ of 10, 30
    or 60 min estimated: what the order search protects the targets against."""
    us = [drift_u(design, visits, times_h, tau) for tau in (None, *WARMUP_TAU_H)]
    return np.max(np.array(us), axis=0)


def max_links(machine: Machine, artefact: Artefact, poses: Sequence[tuple[float, float]]
              ) -> tuple[tuple[str, ...], dict[str, str]]:
    """The identifiable link set of a pose set (and what absorbs the others)."""
    ident = identifiable_links(machine, artefact, nominal_centres(machine, artefact,
                                                                   list(poses)))
    return ident.links, ident.dropped
