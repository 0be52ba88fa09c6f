"""Analyses on top of an estimate: volumetric distortion, cluster, distances, validation.

Vectors are in controller coordinates X, Y, Z (mm inside, µm / µrad in the returned figures).
For the shipped machines the controller origin is the model origin O0 at the nominal
intersection of the rotary axes (thesis §4.4) and the controller axes are a rigid image of the
machine frame, so rigid motions stay rigid and distances are true distances.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from identification.estimate import Estimate, estimate
from identification.kinematics import Machine
from identification.model import Artefact, Centres, predict


@dataclass
class Volumetric:
    """Per centre: ε = measured − predicted (thesis Eq. 3.22 / 4.3 / B.8), µm."""

    before_um: np.ndarray  # (K, 3) prediction: nominal machine + estimated setup only
    after_um: np.ndarray  # (K, 3) prediction: + estimated link errors (and scale)

    @property
    def max_before_um(self) -> float:
        return float(np.linalg.norm(self.before_um, axis=1).max())

    @property
    def max_after_um(self) -> float:
        return float(np.linalg.norm(self.after_um, axis=1).max())


def volumetric(machine: Machine, artefact: Artefact, est: Estimate, centres: Centres
               ) -> Volumetric:
    """Volumetric distortion without (Fig 3.10) and with (Fig 3.11) the link errors."""
    before, _ = predict(machine, artefact, est.layout, est.setup_only(), centres)
    after, _ = predict(machine, artefact, est.layout, est.p, centres)
    return Volumetric((centres.xyz_mm - before) * 1e3, (centres.xyz_mm - after) * 1e3)


@dataclass
class Cluster:
    """Cluster analysis of one pose (thesis §4.4, Eqs 4.4-4.9).

    Relocalisation is reported as the rigid motion carrying the predicted cluster onto the
    measured one: measured ≈ predicted + D + R × predicted. The thesis writes the adjustment
    the other way round (e = ε + D + R × OP, Eq. 4.4), i.e. its (D, R) are minus ours.
    """

    pose: int
    linear_um: np.ndarray | None  # (3,) D; None when fewer than 3 non-collinear balls
    angular_urad: np.ndarray | None  # (3,) R (small rotations about x, y, z)
    local_um: dict[str, np.ndarray]  # ball id → residual after the rigid fit (3,)
    note: str = ""


def _skew_rows(p: np.ndarray) -> np.ndarray:
    """Rows A (n, 3, 6) with A @ [D, R] = D + R × p."""
    n = p.shape[0]
    a = np.zeros((n, 3, 6))
    a[:, :, :3] = np.eye(3)
    # R × p = -p × R = -[p]_x R
    a[:, 0, 4], a[:, 0, 5] = p[:, 2], -p[:, 1]
    a[:, 1, 3], a[:, 1, 5] = -p[:, 2], p[:, 0]
    a[:, 2, 3], a[:, 2, 4] = p[:, 1], -p[:, 0]
    return a


def cluster_fit(predicted_mm: np.ndarray, error_um: np.ndarray, ball_ids: Sequence[str],
                pose: int = 0) -> Cluster:
    """Point-to-point least-squares rigid fit of one pose's error field (Eq. 4.9)."""
    p = np.asarray(predicted_mm, float)
    e = np.asarray(error_um, float)
    if p.shape[0] >= 3:
        centred = p - p.mean(axis=0)
        s = np.linalg.svd(centred, compute_uv=False)
        noncollinear = s[1] > 1e-6 * max(s[0], 1e-12)
    else:
        noncollinear = False
    if not noncollinear:
        # Thesis §4.4: one ball gives rank 3, two balls rank 5; only the translation is
        # meaningful, removed as the mean error; nothing is left to call local distortion.
        d = e.mean(axis=0)
        return Cluster(pose, None, None, {b: e[i] - d for i, b in enumerate(ball_ids)},
                       note=f"{p.shape[0]} ball(s) collinear or fewer than 3: no relocalisation")
    a = _skew_rows(p).reshape(-1, 6)
    # Angles in µrad with positions in mm and errors in µm: R[µrad]·p[mm]·1e-3 = µm.
    a[:, 3:] *= 1e-3
    tau, *_ = np.linalg.lstsq(a, e.ravel(), rcond=None)
    local = e - (a @ tau).reshape(-1, 3)
    return Cluster(pose, tau[:3], tau[3:], {b: local[i] for i, b in enumerate(ball_ids)})


def clusters(centres: Centres, predicted_mm: np.ndarray, error_um: np.ndarray,
             ball_ids: Sequence[str], group: np.ndarray | None = None) -> list[Cluster]:
    """One cluster fit per pose (or per ``group`` label, e.g. pose × repeat)."""
    g = centres.pose if group is None else group
    out = []
    for key in np.unique(g):
        m = g == key
        ids = [ball_ids[i] for i in centres.ball[m]]
        out.append(cluster_fit(predicted_mm[m], error_um[m], ids, int(centres.pose[m][0])))
    return out


@dataclass
class DistanceDev:
    pose: int
    ball_a: str
    ball_b: str
    distance_mm: float
    deviation_um: float  # from the mean over poses of this pair (Annexe A, Eq. A.2)


def distance_analysis(centres: Centres, ball_ids: Sequence[str],
                      group: np.ndarray | None = None) -> list[DistanceDev]:
    """Ball-to-ball distances per pose and their deviation from the mean over poses."""
    g = centres.pose if group is None else group
    per: dict[tuple[int, int], list[tuple[int, float]]] = {}
    for key in np.unique(g):
        idx = np.flatnonzero(g == key)
        for i_pos, i in enumerate(idx):
            for j in idx[i_pos + 1:]:
                a, b = sorted((int(centres.ball[i]), int(centres.ball[j])))
                d = float(np.linalg.norm(centres.xyz_mm[i] - centres.xyz_mm[j]))
                per.setdefault((a, b), []).append((int(centres.pose[i]), d))
    out = []
    for (a, b), vals in sorted(per.items()):
        mean = np.mean([d for _, d in vals])
        out += [DistanceDev(pose, ball_ids[a], ball_ids[b], d, (d - mean) * 1e3)
                for pose, d in vals]
    return out


@dataclass
class Revisit:
    """One ball seen twice at the same indexation: the centre's shift between its first and
    last visit of the run (controller X Y Z) — nothing of the machine's geometry changes it,
    only time: thermal drift of machine or artefact, a loose ball, probe drift."""

    pose: int
    ball: str
    repeat_first: int
    repeat_last: int
    dt_s: float
    shift_um: np.ndarray  # (3,)

    @property
    def norm_um(self) -> float:
        return float(np.linalg.norm(self.shift_um))


def revisits(centres: Centres, repeat: np.ndarray, ball_ids: Sequence[str]) -> list[Revisit]:
    """Every (pose, ball) measured in more than one repeat: last visit − first visit."""
    out = []
    t = centres.t_s if centres.t_s.size == len(centres) else np.full(len(centres), np.nan)
    for pose in np.unique(centres.pose):
        for ball in np.unique(centres.ball[centres.pose == pose]):
            idx = np.flatnonzero((centres.pose == pose) & (centres.ball == ball))
            if np.unique(repeat[idx]).size < 2:
                continue
            first, last = idx[np.argmin(repeat[idx])], idx[np.argmax(repeat[idx])]
            out.append(Revisit(int(pose), ball_ids[int(ball)], int(repeat[first]),
                               int(repeat[last]), float(t[last] - t[first]),
                               (centres.xyz_mm[last] - centres.xyz_mm[first]) * 1e3))
    return out


@dataclass
class Validation:
    """Prediction of held-out poses (annex B §B.5), µm."""

    poses: list[int]
    rms_before_um: float
    rms_after_um: float
    max_before_um: float
    max_after_um: float
    explained_fraction: float  # 1 − max_after / max_before (the thesis' 90 %: 117 → 12 µm)
    explained_fraction_rms: float  # 1 − rms_after / rms_before
    volumetric: Volumetric


def validate(machine: Machine, artefact: Artefact, est: Estimate, centres: Centres
             ) -> Validation:
    """Predict ``centres`` (not used by ``est``) with setup only vs setup + links."""
    v = volumetric(machine, artefact, est, centres)
    nb = np.linalg.norm(v.before_um, axis=1)
    na = np.linalg.norm(v.after_um, axis=1)
    rb, ra = float(np.sqrt(np.mean(nb**2))), float(np.sqrt(np.mean(na**2)))
    return Validation(sorted(int(x) for x in np.unique(centres.pose)), rb, ra,
                      float(nb.max()), float(na.max()), 1.0 - float(na.max() / nb.max()),
                      1.0 - ra / rb, v)


def estimate_and_validate(machine: Machine, artefact: Artefact, centres: Centres,
                          validate_poses: Sequence[int], links: Sequence[str] | None = None,
                          **kw: object) -> tuple[Estimate, Validation]:
    """Estimate on every pose not in ``validate_poses``, then predict those (annex B)."""
    held = np.isin(centres.pose, list(validate_poses))
    if not held.any():
        raise ValueError(f"validation poses {list(validate_poses)} are not in the data "
                         f"(poses: {sorted(int(x) for x in np.unique(centres.pose))})")
    est = estimate(machine, artefact, centres.subset(~held), links, **kw)
    return est, validate(machine, artefact, est, centres.subset(held))
