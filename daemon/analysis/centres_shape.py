"""What centres measured at a single indexation support, said precisely: the artefact's shape
(ball-to-ball distances, rigid best fit to the artefact file and what remains), never link
errors — every link error needs the artefact seen at two or more indexations with the setup
free (METHOD.md §2-3), and the estimate refuses fewer (``identifiability.py``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from itertools import combinations
from typing import Any, Protocol

import numpy as np

from daemon.analysis.touch_centres import CentreData
from identification.frame import kabsch, rotation_vector_deg
from identification.kinematics import Machine
from identification.model import Artefact, Centres, Layout, predict


class Measured(Protocol):
    """What this module needs of a centres input (``centres_input.CentresInput``)."""

    artefact: Artefact
    data: CentreData
    sigma_um: np.ndarray | None
    sigma_from: str
    frame: str
    warnings: list[str]

    @property
    def indexations(self) -> np.ndarray: ...

    def described(self) -> str: ...


@dataclass
class OneIndexation:
    """The result of `rumba analyze` on centres from one indexation (``to_json`` for --json)."""

    log: str
    machine: str
    artefact: str
    measured_by: str
    b_deg: float
    c_deg: float
    centres: int
    repeats: int
    statements: list[str]
    distances: list[dict[str, Any]] = field(default_factory=list)
    rigid_fit: dict[str, Any] | None = None
    repeat_scatter_um: list[float] | None = None
    warnings: list[str] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        return {"log": self.log, "machine": self.machine, "artefact": self.artefact,
                "measured_by": self.measured_by, "indexations": 1,
                "indexation": {"b_deg": self.b_deg, "c_deg": self.c_deg},
                "centres": self.centres, "repeats": self.repeats, "links": {},
                "identifiable": [], "statements": self.statements,
                "distances": self.distances, "rigid_fit": self.rigid_fit,
                "repeat_scatter_um": self.repeat_scatter_um, "warnings": self.warnings}


def _r(x: float, nd: int = 4) -> float:
    return round(float(x), nd)


def one_indexation(machine: Machine, inp: Measured, source: str) -> OneIndexation:
    """Distances, rigid fit and the statements of what one indexation can and cannot give."""
    a, c, rep = inp.artefact, inp.data.centres, inp.data.repeat
    n = len(a.balls)
    b0, c0 = (float(v) for v in inp.indexations[0])
    mean = np.array([c.xyz_mm[c.ball == i].mean(axis=0) for i in range(n)])
    scatter, dof = None, 0
    dev = np.concatenate([c.xyz_mm[c.ball == i] - mean[i] for i in range(n)])
    dof = len(c) - n
    if dof > 0:
        scatter = [_r(v * 1e3) for v in np.sqrt(np.sum(dev**2, axis=0) / dof)]
    frame = inp.frame == "instrument"
    cands = ", ".join(machine.location_error_names())
    st = [f"{len(c)} centres of {n} balls at one indexation (b = {b0:g}°, c = {c0:g}°)"
          + (f", {len(np.unique(rep))} repeats" if len(np.unique(rep)) > 1 else "")
          + ": the setup and the machine cannot be separated without a second indexation.",
          f"Link errors: none identifiable ({cands}: each needs the artefact at two or more "
          "indexations with the setup estimated).",
          "Isotropic scale: not observable (no second length reference)."]
    if frame:
        st.append("Setup and instrument frame: the six frame parameters absorb where the "
                  "cluster lies and how it is turned; what remains is the artefact's shape: the "
                  "ball-to-ball distances and the rigid-fit residuals below, compared with the "
                  "artefact file.")
    else:
        st.append("Setup: the probe offset and the mean ball offset are one translation (not "
                  "separable); the rigid fit's rotation mixes the artefact's orientation with "
                  "the rotary axes' angular errors at this indexation, and its residuals mix "
                  "the artefact's shape with the linear axes' squareness: none separable from "
                  "one indexation.")
    if scatter is None:
        st.append("Uncertainty: no repeat and no stated uncertainty, so no noise floor: the "
                  "deviations below carry no uncertainty (state u_um, repeatability_um or "
                  "--repeatability-um, or measure again)." if inp.sigma_um is None else
                  f"Uncertainty: as stated ({inp.sigma_from}).")
    else:
        st.append(f"Repeat scatter of a centre: {' / '.join(f'{v:.3f}' for v in scatter)} µm "
                  f"x / y / z ({dof} dof).")
    out = OneIndexation(source, machine.name, a.name, inp.described(), b0, c0, len(c),
                        len(np.unique(rep)), st, repeat_scatter_um=scatter,
                        warnings=list(inp.warnings))
    cal = {frozenset((d.ball_a, d.ball_b)): d.distance_mm for d in a.distances}
    nom = a.nominal_mm
    for i, j in combinations(range(n), 2):
        d = float(np.linalg.norm(mean[i] - mean[j]))
        d_nom = float(np.linalg.norm(nom[i] - nom[j]))
        row = {"balls": [a.ids[i], a.ids[j]], "distance_mm": _r(d, 7),
               "artefact_file_mm": _r(d_nom, 7), "deviation_um": _r((d - d_nom) * 1e3)}
        k = frozenset((a.ids[i], a.ids[j]))
        if k in cal:
            row["calibrated_mm"] = cal[k]
            row["deviation_from_calibrated_um"] = _r((d - cal[k]) * 1e3)
        out.distances.append(row)
    if n < 3:
        st.append(f"Rigid fit: {n} ball(s) fix no rotation; only the distances are reported.")
        return out
    one = Centres(np.zeros(n, int), np.arange(n), np.full(n, b0), np.full(n, c0), mean)
    q0, _ = predict(machine, a, Layout((), n), np.zeros(3 * n + 3), one)
    try:
        rot, t = kabsch(q0, mean)
    except ValueError as e:
        st.append(f"Rigid fit: not possible ({e}).")
        return out
    res_um = (mean - (q0 @ rot.T + t)) * 1e3
    rv = rotation_vector_deg(rot)
    out.rigid_fit = {
        "what": ("the nominal prediction (artefact file, nominal machine) moved rigidly onto "
                 "the measured centres; residual = measured − moved prediction"),
        "translation_um": [_r(v * 1e3) for v in t] if not frame else None,
        "translation_mm": [_r(v, 6) for v in t] if frame else None,
        "rotation_urad": [_r(np.radians(v) * 1e6) for v in rv] if not frame else None,
        "rotation_vector_deg": [_r(v, 9) for v in rv] if frame else None,
        "residual_um": {a.ids[i]: [_r(v) for v in res_um[i]] for i in range(n)},
        "residual_rms_um": _r(np.sqrt(np.mean(res_um**2))),
        "residual_max_um": _r(np.max(np.linalg.norm(res_um, axis=1))),
    }
    return out


def render(r: OneIndexation, console: Any) -> None:
    """The readable summary of a one-indexation result (a rich console)."""
    from rich.table import Table

    console.print(f"[bold]RUMBA analysis[/] of {r.log} — machine {r.machine}, artefact "
                  f"{r.artefact}: {r.centres} centres at ONE indexation ({r.measured_by})")
    for s in r.statements:
        console.print(f"• {s}")
    t = Table(title="Ball-to-ball distances")
    for h in ("balls", "measured mm", "artefact file mm", "deviation µm"):
        t.add_column(h, justify="left" if h == "balls" else "right")
    for d in r.distances:
        t.add_row("–".join(d["balls"]), f"{d['distance_mm']:.4f}", f"{d['artefact_file_mm']:.4f}",
                  f"{d['deviation_um']:.3f}")
    console.print(t)
    fit = r.rigid_fit
    if fit is not None:
        t = Table(title="Rigid fit to the artefact file: residual per ball (µm)")
        for h in ("ball", "dx", "dy", "dz"):
            t.add_column(h, justify="right")
        for b, v in fit["residual_um"].items():
            t.add_row(b, *(f"{x + 0.0:.3f}" if abs(x) >= 5e-4 else "0.000" for x in v))
        console.print(t)
        console.print(f"residual RMS {fit['residual_rms_um']:.3f} µm, largest "
                      f"{fit['residual_max_um']:.3f} µm")
    for w in r.warnings:
        console.print(f"[yellow]warning:[/] {w}")
