"""Controller compensation: which changes of the controller's kinematic values hold the links.

Linearised and generic (no per-controller formula): over the given poses and every ball the
sensitivity of the predicted centres to the identified links (``Jl``) and to each controller
value (``Jp``, central differences of ``predict`` on ``apply_changes``) is compared after the
setup columns (ball and stylus offsets, scale if estimated) are projected out, P = I − S S⁺:
what the setup absorbs is invisible to the data and needs no compensation. Each visible value
is the link combination of the same visible effect; the changes hold as much of the identified
links ℓ as those combinations can (``fit="links"``), or match the distortion P Jl ℓ itself,
Δp = (P Jp)⁺ P Jl ℓ (``fit="distortion"``). Units: mm (pivot) and rad (orientation).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from identification.estimate import Estimate
from identification.kinematics import Machine, TopologyError
from identification.model import Artefact, Centres, predict
from identification.uncertainty import expanded_k
from identification.worth import (
    GuardResult,
    Guards,
    after_um,
    check_guards,
    effect_um,
    norms_um,
    worse_after,
)

PIVOT_STEP_MM = 1e-4  # finite-difference steps of the controller values
ORIENTATION_STEP_RAD = 1e-6
RANK_TOL = 1e-6  # relative singular value: the range of the setup columns
# A controller value is visible when its column keeps more than this fraction of its norm once
# the setup is projected out, and is independent of the kept ones by as much (unit columns).
# Not 1e-6: at the estimate the chain carries links of up to ~1e-3 rad, whose cross terms give
# e.g. LinuxCNC's x-rot-point a 3e-5 visible part — a nanometre for a 0.1 mm change.
VISIBLE_TOL = 1e-3
KINDS = ("pivot", "orientation")


@dataclass(frozen=True)
class ControllerParam:
    """One kinematic value the controller holds and a compensation may change."""

    name: str  # the controller's own name, e.g. "x-offset"
    kind: str  # "pivot" | "orientation"
    # pivot: the rotary axes whose point_mm[component] moves by the change (LinuxCNC's
    # x-rot-point moves B and C together; x-offset moves B only); orientation: (axis,)
    axes: tuple[str, ...]
    component: str  # pivot: "x" | "y" | "z"; orientation: the ISO location error it holds


@dataclass(frozen=True)
class ParamChange:
    """The change to ADD to a controller value (model units: mm or rad)."""

    name: str
    kind: str
    delta: float
    u_expanded: float  # expanded uncertainty (coverage_k's coverage, as the judge's), same unit
    observable: bool  # False: the data cannot see it; delta = 0
    note: str = ""


@dataclass
class CompensationPlan:
    """The changes and what they hold of the identified links (model units, µm for figures)."""

    changes: list[ParamChange]
    links_identified: dict[str, float]
    links_compensable: dict[str, float]  # the part of the identified links the params hold
    links_residual: dict[str, float]  # identified − compensable
    distortion_before_um: tuple[float, float]  # (rms, max) link-caused, setup projected out
    distortion_compensable_um: tuple[float, float]  # (rms, max) the part the changes remove
    distortion_after_um: tuple[float, float]  # (rms, max) what is left after the changes
    # the displacements behind those figures (mm, one row per probed centre, setup projected
    # out): the links', and each observable change's own; the worth rule (identification.worth)
    # takes each change's effect and the distortion a subset leaves from them. None / empty
    # for a plan built by hand.
    link_disp_mm: np.ndarray | None = dataclasses.field(default=None, compare=False)
    change_disp_mm: dict[str, np.ndarray] = dataclasses.field(default_factory=dict,
                                                              compare=False)

    def effect_um(self, name: str) -> float | None:
        """The change's own effect: the largest displacement of a probed centre (µm)."""
        return effect_um(self.change_disp_mm.get(name))

    def after_um(self, names: list[str]) -> tuple[float, float]:
        """(RMS, max) link-caused distortion left once the changes ``names`` are written."""
        # a plan built by hand carries only its stated figures
        fallback = self.distortion_after_um if names else self.distortion_before_um
        return after_um(self.link_disp_mm, self.change_disp_mm, names, fallback)


def _check_param(machine: Machine, param: ControllerParam) -> None:
    if param.kind not in KINDS:
        raise ValueError(f"controller value {param.name}: kind {param.kind!r} not in {KINDS}")
    if not param.axes:
        raise ValueError(f"controller value {param.name}: no axis given")
    for a in param.axes:
        if a not in machine.axes or machine.axes[a].kind != "rotary":
            raise TopologyError(f"controller value {param.name}: {a!r} is not a rotary axis "
                                f"of {machine.topology}")
    if param.kind == "pivot":
        if param.component not in ("x", "y", "z"):
            raise ValueError(f"pivot {param.name}: component {param.component!r} must be "
                             "x, y or z")
    else:
        if len(param.axes) != 1:
            raise ValueError(f"orientation {param.name}: exactly one axis, got {param.axes}")
        names = machine.axes[param.axes[0]].location_error_names()
        if param.component not in names:
            raise TopologyError(f"orientation {param.name}: {param.component!r} is not a "
                                f"location error of axis {param.axes[0]} ({names})")


def apply_changes(machine: Machine, params: Sequence[ControllerParam],
                  changes: Sequence[ParamChange]) -> Machine:
    """The controller's model after the changes: a pivot change moves ``point_mm[component]``
    of each of its axes, an orientation change is added to ``held_links``."""
    by_name = {p.name: p for p in params}
    axes = dict(machine.axes)
    held = list(machine.held_links)
    for ch in changes:
        if ch.name not in by_name:
            raise ValueError(f"change of {ch.name!r}: no such controller value "
                             f"(known: {sorted(by_name)})")
        param = by_name[ch.name]
        _check_param(machine, param)
        if not ch.delta:
            continue
        if param.kind == "pivot":
            k = "xyz".index(param.component)
            for a in param.axes:
                pt = list(axes[a].point_mm)
                pt[k] += float(ch.delta)
                axes[a] = dataclasses.replace(axes[a], point_mm=(pt[0], pt[1], pt[2]))
        else:
            held.append((param.component, float(ch.delta)))
    merged: dict[str, float] = {}
    for name, value in held:
        merged[name] = merged.get(name, 0.0) + value
    return dataclasses.replace(machine, axes=axes, held_links=tuple(merged.items()))


def pose_centres(artefact: Artefact, b_deg: np.ndarray, c_deg: np.ndarray) -> Centres:
    """Every ball at every pose (b_deg[i], c_deg[i]); centres to be predicted (zeros)."""
    b = np.atleast_1d(np.asarray(b_deg, float))
    c = np.atleast_1d(np.asarray(c_deg, float))
    if b.shape != c.shape or b.ndim != 1 or b.size == 0:
        raise ValueError(f"b_deg and c_deg must be 1-D of equal, non-zero length "
                         f"({b.shape} vs {c.shape})")
    n = len(artefact.balls)
    pose = np.repeat(np.arange(b.size), n)
    ball = np.tile(np.arange(n), b.size)
    return Centres(pose, ball, b[pose], c[pose], np.zeros((pose.size, 3)))


def param_columns(machine: Machine, artefact: Artefact, est: Estimate,
                  params: Sequence[ControllerParam], centres: Centres) -> np.ndarray:
    """d(predicted centre)/d(controller value) (3K, n_params), central differences of the
    exact chain at the estimate (mm per mm or mm per rad)."""
    out = np.zeros((3 * len(centres), len(params)))
    for i, param in enumerate(params):
        _check_param(machine, param)
        h = PIVOT_STEP_MM if param.kind == "pivot" else ORIENTATION_STEP_RAD
        q = []
        for sgn in (1.0, -1.0):
            m = apply_changes(machine, [param], [ParamChange(param.name, param.kind, sgn * h,
                                                             0.0, True)])
            q.append(predict(m, artefact, est.layout, est.p, centres)[0])
        out[:, i] = ((q[0] - q[1]) / (2 * h)).ravel()
    return out


def _range_basis(s: np.ndarray) -> np.ndarray:
    """Orthonormal basis of the column space of ``s`` (rank-revealing SVD)."""
    norms = np.linalg.norm(s, axis=0)
    u, sv, _ = np.linalg.svd(s / np.where(norms > 0, norms, 1.0), full_matrices=False)
    return u[:, sv > RANK_TOL * sv[0]] if sv.size and sv[0] > 0 else u[:, :0]


def _observable_set(pjp: np.ndarray, jp: np.ndarray, params: Sequence[ControllerParam]
                    ) -> tuple[list[int], dict[int, str]]:
    """Greedy, in the given order: keep a value whose projected column survives the setup and
    raises the rank of the kept ones; the others get the reason they are not observable."""
    kept: list[int] = []
    notes: dict[int, str] = {}
    for i in range(len(params)):
        raw = float(np.linalg.norm(jp[:, i]))
        proj = float(np.linalg.norm(pjp[:, i]))
        if raw == 0.0:
            notes[i] = "has no effect on the measured centres at these poses"
            continue
        if proj <= VISIBLE_TOL * raw:
            notes[i] = ("moves every ball and the stylus alike at these poses: absorbed by the "
                        "setup errors of an uncalibrated artefact (the data cannot see it)")
            continue
        cols = pjp[:, [*kept, i]]
        cols = cols / np.linalg.norm(cols, axis=0)
        sv = np.linalg.svd(cols, compute_uv=False)
        if sv[-1] <= VISIBLE_TOL * sv[0]:
            others = ", ".join(params[k].name for k in kept)
            notes[i] = (f"its visible effect is a combination of {others}: not separable, "
                        "compensated through those")
            continue
        kept.append(i)
    return kept, notes


def plan_compensation(machine: Machine, artefact: Artefact, est: Estimate,
                      params: Sequence[ControllerParam], b_deg: np.ndarray, c_deg: np.ndarray,
                      *, coverage_k: float = 2.0, fit: str = "links") -> CompensationPlan:
    """Controller-value changes holding the identified links (module doc).

    ``fit="links"`` (default): each observable value is expressed as the combination of links
    with the same visible effect, and the changes are the least-squares match of those to the
    identified links, each link weighted by the distortion it alone causes. A value exactly
    equivalent to one link (LinuxCNC's x-offset ≡ −EX0C) then takes that link whole and nothing
    of the others: re-identified against the changed controller, that link is zero.
    ``fit="distortion"``: Δp = (P Jp)⁺ P Jl ℓ, the least-squares match of the distortion at
    these poses; with correlated links it also bends the values towards the links no value can
    hold (cross-talk: the re-identified link is then not zero, e.g. 2.6 µm of EX0C's 106)."""
    if fit not in ("links", "distortion"):
        raise ValueError(f"fit {fit!r}: expected 'links' or 'distortion'")
    names = [p.name for p in params]
    if len(set(names)) != len(names):
        raise ValueError(f"controller value names must be unique: {names}")
    centres = pose_centres(artefact, b_deg, c_deg)
    n_l = len(est.layout.links)
    _, jac = predict(machine, artefact, est.layout, est.p, centres, jacobian=True)
    j = jac.reshape(-1, est.layout.size)
    jl, s = j[:, :n_l], j[:, n_l:]  # links | balls, tip (and scale when estimated)
    basis = _range_basis(s)

    def proj(x: np.ndarray) -> np.ndarray:
        return x - basis @ (basis.T @ x)

    ell = np.asarray(est.p[:n_l], float)
    jp = param_columns(machine, artefact, est, params, centres)
    pjl, pjp = proj(jl), proj(jp)
    kept, notes = _observable_set(pjp, jp, params)

    a = np.zeros((len(params), n_l))  # Δp = A ℓ
    ell_c = np.zeros(n_l)
    if kept and n_l:
        ln = np.linalg.norm(pjl, axis=0)
        ln = np.where(ln > 0, ln, 1.0)
        cols = pjp[:, kept]
        cn = np.linalg.norm(cols, axis=0)
        # Each kept value as the link combination of the same visible effect (unit columns).
        e = (np.linalg.pinv(pjl / ln, rcond=RANK_TOL) @ (cols / cn)) / ln[:, None]
        rest = np.linalg.norm(cols / cn - pjl @ e, axis=0)
        for k, i in enumerate(kept):
            if rest[k] > VISIBLE_TOL:
                notes[i] = (f"{100 * (1 - rest[k]):.1f} % of its visible effect is a "
                            "combination of the identified links; the rest is not held")
        if fit == "links":
            a[kept] = np.linalg.pinv(e * ln[:, None], rcond=RANK_TOL) @ np.diag(ln) / cn[:, None]
        else:
            a[kept] = (np.linalg.pinv(cols / cn, rcond=RANK_TOL) @ pjl) / cn[:, None]
        ell_c = e @ (cn * (a[kept] @ ell))
    dp = a @ ell
    cov_l = est.cov[:n_l, :n_l]
    # k at coverage_k's normal coverage for u on the estimate's dof: the judge's guard band
    k = expanded_k(est.sigma_dof, coverage_k)
    u = k * np.sqrt(np.clip(np.diag(a @ cov_l @ a.T), 0.0, None))
    changes = [ParamChange(p.name, p.kind, float(dp[i]) if i in kept else 0.0,
                           float(u[i]) if i in kept else 0.0, i in kept, notes.get(i, ""))
               for i, p in enumerate(params)]
    held_disp = pjp @ dp  # the distortion the changes reproduce (projected)
    link_disp = pjl @ ell
    links = list(est.layout.links)
    return CompensationPlan(
        changes=changes,
        links_identified={k: float(v) for k, v in zip(links, ell, strict=True)},
        links_compensable={k: float(v) for k, v in zip(links, ell_c, strict=True)},
        links_residual={k: float(v) for k, v in zip(links, ell - ell_c, strict=True)},
        distortion_before_um=norms_um(link_disp),
        distortion_compensable_um=norms_um(held_disp),
        distortion_after_um=norms_um(link_disp - held_disp),
        link_disp_mm=link_disp.reshape(-1, 3),
        change_disp_mm={params[i].name: (pjp[:, i] * dp[i]).reshape(-1, 3) for i in kept},
    )


__all__ = ["KINDS", "CompensationPlan", "ControllerParam", "GuardResult", "Guards",
           "ParamChange", "apply_changes", "check_guards", "param_columns", "plan_compensation",
           "pose_centres", "worse_after"]
