"""Gross faults of single ball visits — a chip, dirt, a coolant drop, a bad trigger: a robust
per-visit outlier test, the touch at fault and its size, and which visit a re-probe replaces.

One touch displaced by δ along its normal moves the five-touch sphere fit (METHOD.md §1, thesis
§3.4) in a way fixed by the probing pattern — four equator diagonals and the pole:

* an equator touch: radius +δ/4 and δ/2 on the one residual no sphere explains (the "form"
  direction (1, −1, 1, −1, 0)/2), centre δ/2 towards that touch. A touch and its opposite give
  the same form and radius: the sphere fit alone cannot tell touch 1 from touch 3;
* the pole: nothing on radius or form (it is the only touch that fixes the centre along the
  spindle); the centre moves by δ along the pole normal — visible only against the model.

Hence two stages, both judged against the run's *own* statistics with the median and the
median absolute deviation (σ ≈ 1.4826 · MAD for a normal sample; Hampel et al., *Robust
Statistics*, 1986), which one bad visit cannot move as it moves a mean or an RMS:

1. sphere: robust z of the fitted radius and of the signed form residual, D = √(z_r² + z_f²);
2. centre: the visit's *deleted* residual (the model fitted without it: hat matrix, Cook &
   Weisberg 1982) against setup + location errors (thesis ch. 4) plus a creep of each ball in
   time (thesis §3.3), minus the median of the other balls of the same pass over that pose
   (what the twin misses for a whole indexation or a whole ball is not a fault of one visit),
   along the pole normal; one-sided, as a chip only ever switches the probe early.

A visit is an outlier when D ≥ ``SPHERE_Z`` or z_c ≥ ``CENTRE_Z`` and the touch at fault departs
by at least ``MIN_SIZE_UM``. The touch: the largest radial deviation of the five from the
centre the rest of the run predicts (the model and the pass's other balls) at the run's median
radius; its size (µm, + outside the ball: an early switch) from the visit's own radius and form
for an equator touch, from that deviation for the pole.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from identification.identifiability import RANK_TOL
from identification.kinematics import Machine
from identification.model import Artefact, Centres, Layout, predict
from identification.spherefit import SphereFitError, fit_spheres

TOUCHES = 5  # 1-4 equator diagonals, 5 the pole (contracts.messages.TOUCH_DIRECTIONS)
MAD_TO_SIGMA = 1.4826  # σ = 1.4826 · MAD for a normal sample (consistency factor)
SPHERE_Z = 7.0  # threshold on D (χ²₂ under the null: P(D ≥ 7) = e^-24.5 ≈ 2e-11 per visit)
CENTRE_Z = 10.0  # threshold on z_c (normal: P(z ≥ 10) ≈ 8e-24 per visit)
# Room for a MAD that underestimates σ (relative spread ≈ 1.1/√visits: 15 % with 56 visits)
# and for tails heavier than normal. Measured (benchmarks/bench_outliers.py, and the gap
# self-check with every library effect withheld from the twin at 5× the floor, 84 cases): the
# largest D 4.8 on null runs and 4.5 with effects — the sphere does not see the machine; the
# largest z_c 3.3 on null runs but 7.9 with effects (a straightness, a rotary positioning error
# the twin lacks): the centre stage leans on the twin, hence its higher threshold. A 10 µm pole
# fault gives z_c ≈ 15-30 at the thesis repeatability.
MIN_SIZE_UM = 2.0  # smaller single-touch deviations move a centre by < 1 µm (≈ the thesis'
# centre repeatability, §3.4): not a gross fault, whatever their z
SUSPECT_Z = 3.5  # first pass: left out of the model fit of the second (Hampel's x84 rule)
MAX_SUSPECT_FRACTION = 0.2  # more suspects than this: the model, not single visits, is off
MIN_VISITS = 8  # fewer visits give no usable median / MAD
GN_ITER = 10
GN_TOL_MM = 1e-7  # the screening model's Gauss-Newton stops when no centre moves 0.1 nm
SCALE_FLOOR_UM = 0.05  # a MAD of exact (simulated, noise-free) data must not divide by ~0
REPROBE_REPEAT_BASE = 100
"""A re-probe of a suspicious visit is logged with repeat = 100 · round + the repeat of the
visit it re-measures (plans have at most 21 repeats): the probing log stays one flat table and
any reader can tell the two visits apart."""


def reprobe_repeat(repeat: int, round_: int) -> int:
    """The repeat number of re-probe ``round_`` (1, 2 …) of the visit logged as ``repeat``."""
    return REPROBE_REPEAT_BASE * round_ + repeat


def split_repeat(repeat: int | np.ndarray) -> tuple:
    """(repeat of the visit re-measured, round): round 0 for a visit of the plan itself."""
    return repeat % REPROBE_REPEAT_BASE, repeat // REPROBE_REPEAT_BASE


@dataclass(frozen=True)
class VisitOutlier:
    """One ball visit that departs from the run: the touch at fault and by how much."""

    index: int  # into the visits screened
    touch: int  # 1..5
    size_um: float  # radial deviation of that touch (+ outside the ball: early switch, chip)
    score: float  # the larger robust statistic (D or |z_c|)
    stage: str  # "sphere" (radius/form of its own fit) | "centre" (vs model and pose)


@dataclass(frozen=True)
class Screening:
    """The outlier test of one run's visits and the robust scales it used (µm)."""

    outliers: tuple[VisitOutlier, ...]
    visits: int
    radius_scale_um: float | None = None
    form_scale_um: float | None = None
    centre_scale_um: float | None = None  # None: centre stage not run (no model fit)
    note: str = ""
    sphere_z: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (G,) D per visit
    centre_z: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (G,) z_c per visit


def robust_scale(x: np.ndarray, floor: float = SCALE_FLOOR_UM) -> tuple[float, float]:
    """(median, σ from the MAD with the 1.4826 consistency factor, at least ``floor``)."""
    med = float(np.median(x))
    return med, max(MAD_TO_SIGMA * float(np.median(np.abs(x - med))), floor)


def form_direction(normals: np.ndarray) -> np.ndarray:
    """(G, 5) unit left null vector of the sphere-fit sensitivity [n_i, 1] per visit: the one
    combination of radial residuals no sphere explains; sign: positive on touch 1."""
    m = np.concatenate([normals, np.ones((*normals.shape[:2], 1))], axis=2)
    u = np.linalg.svd(m)[0][:, :, -1]
    ref = np.where(np.abs(u[:, 0]) > 1e-6, u[:, 0], u.sum(axis=1))
    return u * np.where(ref < 0, -1.0, 1.0)[:, None]


def screening_model(machine: Machine, artefact: Artefact, centres: Centres
                    ) -> tuple[np.ndarray, np.ndarray] | None:
    """The centres' residual (K, 3) µm against setup + every location error of the machine
    (thesis ch. 4) at the Gauss-Newton solution, and the model's design (K, 3, Q) µm per
    parameter unit there, widened by a creep of each ball in time (a velocity in the workpiece
    frame, thesis §3.3: a loose ball drifts on its rod) — what moves one ball over the whole run
    is a deficiency of the twin, not a fault of one visit, and must not make its first or last
    visit stand out. Every location error, not the identifiable set: the fit uses the pseudo-
    inverse (``RANK_TOL``), whose column space is the same, without selecting columns one SVD
    at a time. None when the centres cannot be fitted."""
    layout = Layout(tuple(machine.location_error_names()), len(artefact.balls))
    p = np.zeros(layout.size)
    try:
        with np.errstate(all="ignore"):
            for _ in range(GN_ITER):
                pred, jac = predict(machine, artefact, layout, p, centres, jacobian=True)
                r = centres.xyz_mm - pred
                j = jac.reshape(-1, layout.size)
                step = _solve(j, r.reshape(-1))
                p = p + step
                r = r - (j @ step).reshape(-1, 3)  # the last step, linearly (< 1 nm)
                if np.max(np.abs(j @ step)) < GN_TOL_MM:
                    break
    except (ValueError, np.linalg.LinAlgError, FloatingPointError):
        return None
    design = np.concatenate([jac, *_creep_columns(jac, layout.ball_slice.start, centres)],
                            axis=2)
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(design))):
        return None
    return r * 1e3, design * 1e3


def _solve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Minimum-norm least squares on unit-norm columns, singular values below ``RANK_TOL``
    of the largest dropped (the directions the probing pattern cannot see)."""
    norms = np.linalg.norm(a, axis=0)
    norms[norms == 0] = 1.0
    return np.linalg.lstsq(a / norms, b, rcond=RANK_TOL)[0] / norms


def deleted_residuals_um(residual_um: np.ndarray, design: np.ndarray,
                         exclude: np.ndarray | None = None) -> np.ndarray:
    """(K, 3) residual of each centre against the linearised model (``screening_model``)
    refitted on every centre but itself and the ``exclude``d ones (suspects: their residual is
    a plain prediction error): for the others e_k = (I − H_kk)⁻¹ r_k, H the hat matrix (Cook
    & Weisberg 1982). A centre the fit cannot do without (leverage ~1) gets 0: untestable."""
    keep = np.ones(len(residual_um), bool) if exclude is None else ~np.asarray(exclude, bool)
    q = design.shape[2]
    xk = design[keep].reshape(-1, q)
    norms = np.linalg.norm(xk, axis=0)
    norms[norms == 0] = 1.0
    u, sv, vt = np.linalg.svd(xk / norms, full_matrices=False)
    rank = int(np.sum(sv > RANK_TOL * sv[0])) if sv.size else 0
    u, sv, vt = u[:, :rank], sv[:rank], vt[:rank]
    coef = vt.T @ ((u.T @ residual_um[keep].reshape(-1)) / sv) / norms
    out = residual_um - np.einsum("kaq,q->ka", design, coef)
    uk = u.reshape(-1, 3, rank)
    m = np.eye(3)[None] - np.einsum("kar,kbr->kab", uk, uk)
    ok = np.linalg.det(m) > 1e-9
    kept = np.flatnonzero(keep)
    fixed = np.zeros((len(kept), 3))
    fixed[ok] = np.linalg.solve(m[ok], out[keep][ok][..., None])[..., 0]
    out[kept] = fixed
    return out


def _creep_columns(jac: np.ndarray, ball_start: int, centres: Centres) -> list[np.ndarray]:
    """Per ball: its setup columns × its visits' time about their mean (h), others zero."""
    t = np.asarray(centres.t_s, float)
    if t.shape != (len(centres),) or np.ptp(t) <= 0:
        return []
    out = []
    for b in np.unique(centres.ball):
        on = np.asarray(centres.ball) == b
        if np.count_nonzero(on) < 3:
            continue
        tau = np.where(on, (t - t[on].mean()) / 3600.0, 0.0)
        s = ball_start + 3 * int(b)
        out.append(jac[:, :, s:s + 3] * tau[:, None, None])
    return out


def _pose_contrast(resid_um: np.ndarray, group: np.ndarray) -> np.ndarray:
    """Each visit's residual minus the median of the other balls of its pass over the pose
    (``group``: one label per pose and repeat; 3 or more visits there): what the model misses
    for one indexation — rotary positioning, a rigid jump, a drift between two passes — is
    not a fault of one visit."""
    out = resid_um.copy()
    _, inverse, counts = np.unique(group, return_inverse=True, return_counts=True)
    order = np.argsort(inverse.reshape(-1), kind="stable")
    starts = np.r_[0, np.cumsum(counts)[:-1]]
    for n in np.unique(counts[counts >= 3]):  # passes of equal size together (vectorised)
        members = order[starts[counts == n][:, None] + np.arange(n)]  # (m, n)
        vals = resid_um[members]  # (m, n, 3)
        for k in range(n):
            others = np.delete(vals, k, axis=1)
            out[members[:, k]] = vals[:, k] - np.median(others, axis=1)
    return out


def screen(points_mm: np.ndarray, nominal_radius_mm: np.ndarray, group: np.ndarray,
           residual_um: np.ndarray | None = None) -> Screening:
    """The test on (G, 5, 3) touch points (touch 1..5 in order) with their nominal radii
    (ball + stylus, mm) and pass labels (``group``: one per pose and repeat); ``residual_um``
    (G, 3): each visit's deleted centre residual against the model (``deleted_residuals_um``),
    None to skip the centre stage."""
    pts = np.asarray(points_mm, float)
    g = pts.shape[0]
    if g < MIN_VISITS:
        return Screening((), g, note=f"{g} ball visits: too few for a robust outlier test "
                                     f"(needs {MIN_VISITS})")
    r_nom = np.broadcast_to(np.asarray(nominal_radius_mm, float), (g,))
    try:
        fit = fit_spheres(pts, r_nom)
    except SphereFitError as e:
        return Screening((), g, note=f"outlier test skipped: sphere fit failed: {e.reason}")
    diff = pts - fit.centre_mm[:, None, :]
    dist = np.linalg.norm(diff, axis=2)
    normal = diff / dist[..., None]
    radial_um = (dist - fit.radius_mm[:, None]) * 1e3
    w = form_direction(normal)
    form = np.einsum("gt,gt->g", w, radial_um)
    med_r, s_r = robust_scale(fit.radius_dev_um)
    med_f, s_f = robust_scale(form)
    d_sphere = np.hypot((fit.radius_dev_um - med_r) / s_r, (form - med_f) / s_f)
    z_c = np.zeros(g)
    s_c = None
    contrast = None
    note = ""
    if residual_um is not None:
        contrast = _pose_contrast(np.asarray(residual_um, float), np.asarray(group))
        along = np.einsum("gi,gi->g", contrast, normal[:, TOUCHES - 1])
        med_c, s_c = robust_scale(along)
        z_c = (along - med_c) / s_c
    else:
        note = ("centre stage skipped (no model fit): a fault of the pole touch is not seen, "
                "and an equator touch may be its opposite")
    # Where the rest of the run puts this ball: the model and the pose's other balls (the
    # measured centre minus its contrast residual), at the run's median radius.
    expected = fit.centre_mm if contrast is None else fit.centre_mm - contrast * 1e-3
    radius = r_nom + med_r * 1e-3
    dev_um = (np.linalg.norm(pts - expected[:, None, :], axis=2) - radius[:, None]) * 1e3
    # d(radius)/d(radial change of each touch) of the free fit: 1/4 at an equator touch
    m = np.concatenate([normal, np.ones((g, TOUCHES, 1))], axis=2)
    to_radius = np.linalg.pinv(m)[:, 3, :]
    out = []
    # The centre stage is one-sided: a chip, dirt, coolant or an early trigger switches the
    # probe before the ball (outside); a model deficiency is as likely either way.
    for k in np.flatnonzero((d_sphere >= SPHERE_Z) | (z_c >= CENTRE_Z)):
        t = int(np.argmax(np.abs(dev_um[k])))
        size = float(dev_um[k, t])
        a_r, a_f = to_radius[k, t], w[k, t]
        if abs(a_f) >= 0.25:
            # An equator touch: its own fit measures δ twice (radius δ·a_r, form δ·a_f, with
            # the touch noise only), better than against the model's centre prediction.
            y_r, y_f = fit.radius_dev_um[k] - med_r, form[k] - med_f
            size = float((a_r * y_r / s_r**2 + a_f * y_f / s_f**2)
                         / (a_r**2 / s_r**2 + a_f**2 / s_f**2))
        by_sphere = d_sphere[k] / SPHERE_Z >= z_c[k] / CENTRE_Z
        if abs(size) < MIN_SIZE_UM or (not by_sphere and size < 0):
            continue
        out.append(VisitOutlier(int(k), t + 1, size,
                                float(max(d_sphere[k], abs(z_c[k]))),
                                "sphere" if by_sphere else "centre"))
    return Screening(tuple(out), g, s_r, s_f, s_c, note, d_sphere, z_c)


def find_outliers(machine: Machine, artefact: Artefact, centres: Centres,
                  points_mm: np.ndarray, nominal_radius_mm: np.ndarray,
                  repeat: np.ndarray | None = None) -> Screening:
    """Both stages on one run's visits (``repeat``: each visit's, so that the pose's other
    balls are those of the same pass): free-radius sphere fits of ``points_mm`` (G, 5, 3) for
    the centres (whatever fit the analysis uses), deleted residuals against the screening
    model, then ``screen``. Twice: a faulty visit pulls the least-squares fit (a 30 µm pole
    fault shifts its ball's other visits by ~2 µm and doubles the MAD), so the visits suspect
    after the first pass (``SUSPECT_Z``) are left out of the second fit."""
    pts = np.asarray(points_mm, float)
    rep = np.zeros(len(pts), int) if repeat is None else np.asarray(repeat, int)
    group = np.unique(np.stack([centres.pose, rep], axis=1), axis=0, return_inverse=True)[1]
    group = group.reshape(-1)
    if len(pts) < MIN_VISITS:
        return screen(pts, nominal_radius_mm, group)
    try:
        fit = fit_spheres(pts, nominal_radius_mm)
    except SphereFitError as e:
        return Screening((), len(pts), note=f"outlier test skipped: sphere fit failed: "
                                            f"{e.reason}")
    free = Centres(centres.pose, centres.ball, centres.b_deg, centres.c_deg, fit.centre_mm,
                   centres.t_s)
    model = screening_model(machine, artefact, free)
    if model is None:
        return screen(pts, nominal_radius_mm, group)
    first = screen(pts, nominal_radius_mm, group, deleted_residuals_um(*model))
    suspect = (first.sphere_z >= SUSPECT_Z) | (np.abs(first.centre_z) >= SUSPECT_Z)
    if not suspect.any() or suspect.sum() > MAX_SUSPECT_FRACTION * len(pts):
        return first
    return screen(pts, nominal_radius_mm, group, deleted_residuals_um(*model, exclude=suspect))


@dataclass(frozen=True)
class Resolution:
    """Which visits an analysis uses once outliers and re-probes are known."""

    use: np.ndarray  # (G,) bool
    repeat: np.ndarray  # (G,) the repeat each visit stands for (a re-probe: its original's)
    status: dict[int, str]  # outlier index → "repaired" | "unrepaired" | "not used"
    replaced_by: dict[int, int]  # repaired outlier index → index of the visit used instead


def resolve(repeat: np.ndarray, pose: np.ndarray, ball: np.ndarray,
            outliers: Sequence[int]) -> Resolution:
    """Per ball-pose slot (the plan's repeat, pose, ball) the first visit without a fault in
    probing order (the plan's own, then re-probe rounds) is used, standing for that slot. A
    faulty visit before it is ``repaired``; one after it (a re-probe that met a fault while
    the visit it re-measured was clean) is ``not used``; when every visit of a slot is
    faulty, none is used and each is ``unrepaired``."""
    repeat = np.asarray(repeat, int)
    orig, rnd = split_repeat(repeat)
    bad = set(int(i) for i in outliers)
    use = np.zeros(len(repeat), bool)
    status: dict[int, str] = {}
    replaced: dict[int, int] = {}
    slots: dict[tuple[int, int, int], list[int]] = {}
    for i, key in enumerate(zip(orig.tolist(), np.asarray(pose).tolist(),
                                np.asarray(ball).tolist(), strict=True)):
        slots.setdefault(key, []).append(i)
    for visits in slots.values():
        visits.sort(key=lambda i: int(rnd[i]))
        clean = [i for i in visits if i not in bad]
        if not clean:
            status.update({i: "unrepaired" for i in visits})
            continue
        chosen = clean[0]
        use[chosen] = True
        for i in visits:
            if i in bad:
                before = rnd[i] < rnd[chosen]
                status[i] = "repaired" if before else "not used"
                if before:
                    replaced[i] = chosen
    return Resolution(use, orig.astype(int), status, replaced)
