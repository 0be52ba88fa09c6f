"""Touches → ball-pose groups: sphere fits, per-touch sensitivities, and the probing noise floor.

Each (repeat, pose, ball) group of five touches gives four numbers the gap diagnosis works on:
the fitted centre (x, y, z, controller mm) and the *form residual* — the one component of the
five radial residuals that no sphere explains (5 touches − 4 sphere parameters, METHOD.md §1).
The fitted radius is a free per-group parameter and carries nothing into the gap: an effect
that only changes it (uniform pre-travel) is absorbed by the stylus setup (thesis §3.4).

A small offset δ_i of touch i changes its radial residual by n_i·δ_i (n_i the outward normal);
the linearised sphere fit maps these radial changes to (δcentre, δradius) through pinv(M) with
M rows [n_i, 1], and leaves (I − M pinv M) in the residuals. These operators let every effect be
expressed as a change of the four numbers per group, exactly to first order.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from identification.model import Artefact, Centres
from identification.outliers import robust_scale
from identification.spherefit import SphereFitError, fit_spheres

TOUCHES = 5


@dataclass
class TouchData:
    """One row per touch (arrays of length N); units controller mm, deg, s."""

    repeat: np.ndarray
    pose: np.ndarray
    ball: np.ndarray  # index into the artefact
    touch: np.ndarray  # 1..5
    t_s: np.ndarray
    b_deg: np.ndarray
    c_deg: np.ndarray
    direction: np.ndarray  # (N, 3) approach direction of the tool, machine frame
    xyz_mm: np.ndarray  # (N, 3) latched

    def __len__(self) -> int:
        return int(self.pose.shape[0])


@dataclass
class Groups:
    """Sphere-fit results per (repeat, pose, ball) group and the per-touch sensitivities."""

    centres: Centres  # fitted centres; ``t_s`` = mean touch time
    repeat: np.ndarray  # (G,)
    touch_index: np.ndarray  # (G, 5) rows of the TouchData, ordered by touch number 1..5
    normal: np.ndarray  # (G, 5, 3) outward unit normals at the touches
    radial_res_um: np.ndarray  # (G, 5) |p - c| - R, µm
    radius_dev_um: np.ndarray  # (G,) fitted − nominal radius, µm
    radius_mm: np.ndarray  # (G,) fitted radius
    to_centre: np.ndarray  # (G, 3, 5) radial change (mm) → centre shift (mm)
    form_dir: np.ndarray  # (G, 5) unit vector of the sphere-free residual, sign-aligned
    form_um: np.ndarray  # (G,) form residual (µm): radial residuals projected on form_dir
    sigma_touch_um: float  # trigger repeatability estimated from the form residuals
    sigma_dof: int
    centre_cov_um2: np.ndarray  # (G, 3, 3) centre covariance from the touch noise
    dropped: int = 0  # incomplete (fewer than five touches) groups left out
    # observations per group: 4 (centre x y z + form residual) or 3 when there is no usable
    # form residual — centres without touches, exact touches (``gap.centres_input``)
    channels: int = 4

    def __len__(self) -> int:
        return len(self.centres)

    def with_sigma(self, sigma_um: float, dof: int) -> Groups:
        """The same groups with another touch repeatability (covariances rescaled)."""
        k = (sigma_um / self.sigma_touch_um) ** 2
        return replace(self, sigma_touch_um=sigma_um, sigma_dof=dof,
                       centre_cov_um2=self.centre_cov_um2 * k)

    def obs_um(self) -> np.ndarray:
        """The (G, 4) observation per group: centre x, y, z (µm) and form residual (µm)."""
        return np.concatenate([self.centres.xyz_mm * 1e3, self.form_um[:, None]], axis=1)

    def radial_effect(self, radial_mm: np.ndarray) -> np.ndarray:
        """(G, 4) change of the observations (µm) for radial touch deviations (G, 5) mm."""
        dc = np.einsum("gkt,gt->gk", self.to_centre, radial_mm)
        df = np.einsum("gt,gt->g", self.form_dir, radial_mm)
        return np.concatenate([dc, df[:, None]], axis=1) * 1e3

    def touch_effect(self, offset_mm: np.ndarray) -> np.ndarray:
        """(G, 4) change of the observations (µm) for per-touch offsets (N, 3) mm."""
        d = offset_mm[self.touch_index]  # (G, 5, 3)
        return self.radial_effect(np.einsum("gti,gti->gt", self.normal, d))


def group_touches(data: TouchData, artefact: Artefact, stylus_radius_mm: float) -> Groups:
    """Fit a free-radius sphere per complete group and build the sensitivity operators."""
    keys = np.stack([data.repeat, data.pose, data.ball], axis=1)
    uniq, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    idx = np.full((len(uniq), TOUCHES), -1)
    for row, (g, k) in enumerate(zip(inv, data.touch, strict=True)):
        if not 1 <= k <= TOUCHES:
            raise ValueError(f"touch number {k} outside 1..{TOUCHES}")
        if idx[g, k - 1] >= 0:
            raise ValueError(f"duplicated touch {k} in repeat/pose/ball {tuple(uniq[g])}")
        idx[g, k - 1] = row
    complete = np.all(idx >= 0, axis=1)
    if not complete.any():
        raise ValueError("no ball-pose has all five touches")
    uniq, idx = uniq[complete], idx[complete]
    # Order groups by time so that folds and time blocks follow the run.
    t_g = data.t_s[idx].mean(axis=1)
    order = np.argsort(t_g, kind="stable")
    uniq, idx, t_g = uniq[order], idx[order], t_g[order]
    pts = data.xyz_mm[idx]
    r_nom = np.array([artefact.balls[b].diameter_mm / 2 for b in uniq[:, 2]]) + stylus_radius_mm
    try:
        fit = fit_spheres(pts, r_nom)
    except SphereFitError as e:
        if not e.groups:
            raise
        rep, pose, ball = (int(v) for v in uniq[e.groups[0]])
        raise ValueError(f"ball {artefact.ids[ball]} pose {pose} repeat {rep}: sphere fit "
                         f"failed: {e.reason}") from None
    diff = pts - fit.centre_mm[:, None, :]
    dist = np.linalg.norm(diff, axis=2)
    normal = diff / dist[..., None]
    radial_um = (dist - fit.radius_mm[:, None]) * 1e3
    m = np.concatenate([normal, np.ones((*normal.shape[:2], 1))], axis=2)  # (G, 5, 4)
    pinv = np.linalg.pinv(m)  # (G, 4, 5)
    u, _, _ = np.linalg.svd(m)
    form_dir = u[:, :, -1]  # left null vector: the residual no sphere explains
    ref = form_dir[0]
    form_dir *= np.sign(np.einsum("gt,t->g", form_dir, ref))[:, None]
    form_um = np.einsum("gt,gt->g", form_dir, radial_um)
    sigma, dof = form_floor_um(form_um)
    sigma = max(sigma, 1e-3)  # a noise-free simulation still needs a finite weight
    mtm_inv = np.linalg.inv(np.einsum("gti,gtj->gij", m, m))
    cov = sigma**2 * mtm_inv[:, :3, :3]
    centres = Centres(uniq[:, 1].astype(int), uniq[:, 2].astype(int),
                      data.b_deg[idx].mean(axis=1), data.c_deg[idx].mean(axis=1),
                      fit.centre_mm, t_g)
    return Groups(centres, uniq[:, 0].astype(int), idx, normal, radial_um,
                  np.asarray(fit.radius_dev_um, float), np.asarray(fit.radius_mm, float),
                  pinv[:, :3, :], form_dir, form_um,
                  sigma, dof, cov, int((~complete).sum()))


def visit_ids(groups: Groups) -> np.ndarray:
    """One id per indexation (visit): (repeat, pose)."""
    return groups.repeat.astype(np.int64) * 1_000_000 + groups.centres.pose


REJECT_Z = 3.5  # Hampel's x84 rule: beyond 3.5 σ (5.2 MADs) of the median a value is gross


def form_floor_um(form_um: np.ndarray) -> tuple[float, int]:
    """Trigger repeatability (µm) and its dof from the groups' form residuals, once the
    pattern common to all groups is removed (a repeatable lobing is an effect, not noise).
    Robust, yet as efficient as the RMS on clean data: the values beyond ``REJECT_Z`` robust
    σ (median, MAD × 1.4826) of the median are left out, the rest give the RMS about their
    mean — one bad visit (a chip) no longer inflates the floor by its square."""
    if len(form_um) < 2:
        return float(np.sqrt(np.sum(form_um**2))), 1
    med, s = robust_scale(form_um, floor=0.0)
    kept = form_um[np.abs(form_um - med) <= REJECT_Z * s]
    if s < 1e-6 or len(kept) < 2:  # exact (simulated) touches: nothing to call gross
        kept = form_um
    dev = kept - kept.mean()
    dof = len(kept) - 1
    return float(np.sqrt(np.sum(dev**2) / dof)), dof


def repeat_scatter_um(groups: Groups) -> tuple[np.ndarray, int] | None:
    """Centre scatter between repeats per controller axis (std x, y, z µm, and its dof),
    pooled over the (pose, ball) measured more than once; None without repeats.

    Per axis: a probe's centre repeatability is anisotropic (thesis §3.4: 0.66 / 0.98 /
    0.44 µm), and one pooled number would make the noisiest axis look like a gap. Only
    repeats that pass over most of the plan count: a single pose probed again at the end
    (the plan's ``drift_check``) measures the drift over the whole run, the very thing the
    diagnosis must be able to name. For the same reason the shift common to all centres of a
    pass is removed (a drift between passes moves them alike; it is an effect, not scatter),
    at the cost of one dof per extra pass. Before both rules a 3.7 µm X drift over the
    14-pose run came out ``none`` at a "floor" it had inflated itself."""
    c = groups.centres
    poses_in = {int(r): np.unique(c.pose[groups.repeat == r]).size
                for r in np.unique(groups.repeat)}
    full = max(poses_in.values())
    passes = [r for r, n in poses_in.items() if 2 * n >= full]
    use = np.isin(groups.repeat, passes)
    key = c.pose * 100000 + c.ball
    res, rep, n_free = [], [], 0
    for k in np.unique(key[use]):
        m = use & (key == k)
        if m.sum() > 1:
            x = c.xyz_mm[m] * 1e3
            res.append(x - x.mean(axis=0))
            rep.append(groups.repeat[m])
            n_free += int(m.sum()) - 1
    if not res:
        return None
    r_all, rep_all = np.concatenate(res), np.concatenate(rep)
    used = np.unique(rep_all)
    for r in used:
        r_all[rep_all == r] -= r_all[rep_all == r].mean(axis=0)
    dof = n_free - (len(used) - 1)
    if dof <= 0:
        return None
    return np.sqrt(np.sum(r_all ** 2, axis=0) / dof), int(3 * dof)


def repeat_floor_um(groups: Groups) -> tuple[float, int] | None:
    """The scatter between repeats as one number (RMS over x, y, z; µm) and its dof."""
    rep = repeat_scatter_um(groups)
    return None if rep is None else (float(np.sqrt(np.mean(rep[0] ** 2))), rep[1])
