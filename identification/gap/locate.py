"""Where the held-out gap lies: residual breakdowns by pose, ball, axis, approach direction,
time and region of the volume, each cell tested against the noise floor.

A cell's statistic is its whitened held-out sum of squares over its pure-noise expectation
(F-distributed, the floor being estimated too; ``linear.HeldOut``); the approach-direction
cells test the *mean* radial touch residual per direction (a repeatable pattern, thesis §3.4)
with a t statistic. Cells are
significant at a family-wise level ``ALPHA`` (Bonferroni over every cell tested).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from identification.gap.data import Groups
from identification.gap.linear import HeldOut
from identification.tails import f_sf, t_sf

ALPHA = 1e-3


@dataclass(frozen=True)
class Cell:
    by: str
    key: str
    n: int  # number of observations
    rms_um: float
    ratio: float  # mean square over the floor expectation (1 = at the floor); reported as
    # its square root (an RMS ratio) in ``as_dict``
    p_value: float
    significant: bool = False

    def as_dict(self) -> dict:
        return {"by": self.by, "key": self.key, "rms_um": round(self.rms_um, 3),
                "ratio_to_floor": round(float(np.sqrt(self.ratio)), 2), "n": self.n,
                "p_value": float(f"{self.p_value:.3g}")}


def _fmt_angle(v: float) -> str:
    return f"{v:g}"


def breakdowns(groups: Groups, ho: HeldOut, ball_ids: list[str],
               t_block_s: float | None = None) -> list[Cell]:
    """Every cell of every breakdown, significance flagged (Bonferroni over all cells)."""
    c = groups.centres
    g = ho.index
    e_um, e_w = ho.e_um, ho.e_w
    cells: list[Cell] = []

    def chi_cell(by: str, key: str, mask: np.ndarray, cols: slice | int = slice(None)) -> None:
        eu = e_um[mask][:, cols]
        ew = e_w[mask][:, cols]
        obs = ho.expected[mask][:, cols] > 0  # live observations only (data.Groups.channels)
        n = int(np.count_nonzero(obs))
        if n == 0:
            return
        # Expected square per observation = 1 + its leverage (centre coordinates lean on the
        # setup parameters much more than the form residual does).
        ratio = float(np.sum(ew**2) / np.sum(ho.expected[mask][:, cols]))
        # F(n, dof_σ), not χ²(n): the floor itself is estimated from the form residuals.
        p = f_sf(ratio, n, groups.sigma_dof)
        cells.append(Cell(by, key, n, float(np.sqrt(np.mean(eu[obs] ** 2))), ratio, p))

    poses = sorted(set(zip(c.b_deg[g].round(3), c.c_deg[g].round(3), strict=True)))
    for b, cc in poses:
        m = (c.b_deg[g].round(3) == b) & (c.c_deg[g].round(3) == cc)
        chi_cell("pose", f"b={_fmt_angle(b)},c={_fmt_angle(cc)}", m)
    for bi in np.unique(c.ball[g]):
        chi_cell("ball", ball_ids[int(bi)], c.ball[g] == bi)
    for k, name in enumerate("XYZ"):
        chi_cell("axis", name, np.ones(len(g), bool), k)
    t = c.t_s[g]
    if t.size and np.ptp(t) > 0:
        span = t_block_s or max(np.ptp(t) / 4.0, 1e-9)
        blocks = np.floor((t - t.min()) / span).astype(int)
        blocks = np.minimum(blocks, max(int(np.ceil(np.ptp(t) / span)) - 1, 0))
        for k in np.unique(blocks):
            lo = t.min() + k * span
            digits = 0 if span >= 300 else 1
            chi_cell("time", f"{lo / 60:.{digits}f}-{(lo + span) / 60:.{digits}f} min",
                     blocks == k)
    xyz = c.xyz_mm[g]
    med = np.median(xyz, axis=0)
    octant = (xyz > med).astype(int)
    for code in np.unique(octant, axis=0):
        m = np.all(octant == code, axis=1)
        key = "".join(f"{a}{'+' if s else '-'}" for a, s in zip("XYZ", code, strict=True))
        chi_cell("region", key, m)
    if groups.channels == 4:  # the touch directions live in the form residual
        cells += _direction_cells(groups, ho)
    m_tests = max(len(cells), 1)
    return [Cell(x.by, x.key, x.n, x.rms_um, x.ratio, x.p_value, x.p_value < ALPHA / m_tests)
            for x in cells]


def _direction_cells(groups: Groups, ho: HeldOut) -> list[Cell]:
    """Held-out radial touch residual per approach direction, after the sphere fit and the
    twin's predicted sphere distortion: the form residual spread on the five touches. Its mean
    over the groups is what a direction-dependent pre-travel (lobing) leaves once centre and
    radius have absorbed the rest (thesis §3.4); t-tested against its scatter."""
    g = ho.index
    rad = ho.e_um[:, 3:4] * groups.form_dir[g]
    out = []
    n = rad.shape[0]
    if n < 3:
        return out
    for k in range(rad.shape[1]):
        r = rad[:, k]
        sd = max(float(np.std(r, ddof=1)), groups.sigma_touch_um * 0.5)
        tstat = float(np.mean(r) / (sd / np.sqrt(n)))
        p = 2 * t_sf(abs(tstat), n - 1)
        ratio = float(np.mean(r**2) / max(groups.sigma_touch_um**2, 1e-12))
        out.append(Cell("direction", f"touch {k + 1}", n, float(np.sqrt(np.mean(r**2))), ratio, p))
    return out


MAX_SHOWN = 10  # "gap at …" lines in a report; the others are counted


def shown_locations(location: list[dict], breakdowns: list[dict], limit: int = MAX_SHOWN
                    ) -> tuple[list[dict], int, int]:
    """The report's ``location`` cells worth a line — above the floor (RMS ratio > 1),
    significant first, largest first, at most ``limit`` — and the counts of the others: more
    above the floor, and at or below it (e.g. an approach direction whose mean residual is
    significant while its RMS stays under the floor). Each shown cell gets ``significant``."""
    sig = {(c["by"], c["key"]) for c in breakdowns if c.get("significant")}
    above = [dict(c, significant=(c["by"], c["key"]) in sig) for c in location
             if c["ratio_to_floor"] > 1.0]
    above.sort(key=lambda c: (not c["significant"], -c["ratio_to_floor"]))
    return above[:limit], max(len(above) - limit, 0), len(location) - len(above)
