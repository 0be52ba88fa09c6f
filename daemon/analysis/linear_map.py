"""`rumba map`'s analysis: probing logs of one or more placements → the map of the linear axes
(``identification.linmap``) → the ``contracts.linear_map`` document, its figures judged against
a volumetric limit as the daily check's are (``daemon.analysis.judge``)."""

from __future__ import annotations

import datetime
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from contracts import linear_map as doc
from contracts.probing_log import read_log
from contracts.setup_files import MachineFile, load_artefact, load_machine
from daemon.analysis.judge import _grade
from daemon.analysis.touch_centres import rows_to_centres, screen_centres
from daemon.machines.tolerances import Limit
from identification.kinematics import Machine
from identification.linmap.basis import component_names
from identification.linmap.field import (
    GRID_N,
    MapModel,
    box_from_ranges,
    predict_field,
)
from identification.linmap.fit import MapEstimate, MapOptions, fit_map
from identification.linmap.holdout import holdout_residual_mm
from identification.linmap.problem import Placement
from identification.uncertainty import expanded_k

FIGURE_N = 9  # figures on a 9³ grid over the covered box
SAMPLES = 21  # samples of each function over its covered range
RIGID = (f"the field minus its least-squares rigid-body motion (translation and small rotation "
         f"about the centroid) over a {GRID_N}×{GRID_N}×{GRID_N} grid spanning the covered "
         "box: a map is defined up to a rigid motion (the balls' setup takes up any), and the "
         "u are those of this field (its rigid part, carrying the setup's uncertainty, is gone)")
REFIT = ("each ball centre re-fitted from its five touches in the frame the estimate corrects "
         "(links, map, setups: the chain's tip − ball), twice, so that the sphere's shear by "
         "squareness and motion-error slopes does not bias the centres")


@dataclass
class MapRun:
    document: doc.LinearMapFile
    model: MapModel
    estimate: MapEstimate
    machine: Machine


@dataclass
class _Loaded:
    placement: Placement
    log: str
    artefact_file: str
    run_id: str | None
    warnings: list[str]


def load_placement(machine: Machine, name: str, log: Path | str, artefact_path: Path | str,
                   stylus_radius_mm: float, fixed_radius: bool) -> _Loaded:
    """A probing log and its artefact file → a placement with its touches, its faulty ball
    visits left out (re-probes used) by the daily check's outlier test
    (``touch_centres.screen_centres``). Its centre stage leans on the twin without the map,
    whose residuals then set a wide robust scale (3-14 µm on simulated mapped runs, none
    flagged): the sphere stage (radius, form) is what guards a map."""
    artefact = load_artefact(artefact_path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rows = read_log(log, artefact)
        data = rows_to_centres(rows, artefact, stylus_radius_mm, fixed_radius, source=str(log))
    used, _ = screen_centres(machine, artefact, data)
    run = sorted({r.run_id for r in rows})
    read = [str(w.message) for w in caught]
    return _Loaded(Placement(name, artefact, used.centres, used.points_mm,
                             used.radius_nominal_mm, fixed_radius),
                   str(log), str(artefact_path), run[0] if run else None,
                   read + [w for w in used.warnings if w not in read])


def model_of(machine: Machine, est: MapEstimate) -> MapModel:
    n = est.layout.n_model
    return MapModel(machine, est.layout.links, est.basis, est.p[:n], est.cov[:n, :n],
                    box_from_ranges(machine, est.basis.ranges_mm))


def _functions(machine: Machine, est: MapEstimate, model: MapModel) -> list[doc.Function]:
    out = []
    basis, s = est.basis, est.layout.map_slice
    coef, cov = est.p[s], est.cov[s, s]
    degrees = est.order.degrees if est.order else {}
    for axis in "XYZ":
        lo, hi = model.box_mm[axis]
        x = np.linspace(lo, hi, SAMPLES)
        q = x * machine.axes[axis].sign
        vals = basis.values(axis, q)
        idx = basis.axis_terms(axis)
        for slot, name in enumerate(component_names(axis)):
            mine = [j for j, i in enumerate(idx) if basis.terms[i].slot == slot]
            gi = [idx[j] for j in mine]
            k = 1e6 if slot >= 3 else 1e3
            v = vals[:, mine] @ coef[gi] * k
            var = np.einsum("ni,ij,nj->n", vals[:, mine], cov[np.ix_(gi, gi)], vals[:, mine])
            terms = [doc.Term(name=basis.terms[i].name, degree=basis.terms[i].degree,
                              value=float(coef[i] * k), std=float(np.sqrt(cov[i, i]) * k))
                     for i in gi]
            top = degrees.get(axis, max([t.degree for t in terms], default=0))
            absorbed = {t: by for t, by in est.observability.dropped_terms.items()
                        if t.startswith(name + "_P") and int(t.split("_P")[1]) <= max(top, 1)}
            kind = ("positioning" if slot == "XYZ".index(axis) else
                    "angular" if slot >= 3 else "straightness")
            out.append(doc.Function(
                name=name, axis=axis, kind=kind, unit="urad" if slot >= 3 else "um",
                terms=terms, x_mm=[float(a) for a in x], value=[float(a) for a in v],
                u=[float(a) for a in np.sqrt(np.clip(var, 0, None)) * k], absorbed=absorbed))
    return out


def _figures(model: MapModel, limit: Limit | None, source: str | None, k: float
             ) -> doc.Figures:
    pred = predict_field(model, model.grid(FIGURE_N), check=False)
    norm = np.linalg.norm(pred.error_um, axis=1)
    i = int(np.argmax(norm))
    n_hat = pred.error_um[i] / norm[i] if norm[i] > 0 else np.zeros(3)
    jn = n_hat @ pred.jac[i]
    u = float(np.sqrt(max(jn @ model.cov @ jn, 0.0)) * 1e3)
    status = text = None
    if limit is not None:
        checks = _grade("volumetric error max (map)", float(norm[i]), u, "µm", limit, k, None)
        if checks:
            status, text = checks[0].status, checks[0].limit
    at = model.grid(FIGURE_N)[i]
    return doc.Figures(
        volumetric_max_um=doc.Figure(value_um=float(norm[i]), u_um=u,
                                     at_mm=[float(a) for a in at], status=status, limit=text,
                                     source=source),
        volumetric_rms_um=float(np.sqrt(np.mean(norm**2))), points=len(norm),
        grid=f"{FIGURE_N}×{FIGURE_N}×{FIGURE_N} over the covered box, rigid convention")


def _holdout(machine: Machine, loaded: _Loaded, est: MapEstimate, base: MapEstimate
             ) -> doc.Holdout:
    after = holdout_residual_mm(machine, loaded.placement, est.layout, est.p) * 1e3
    before = holdout_residual_mm(machine, loaded.placement, base.layout, base.p) * 1e3
    rms = [float(np.sqrt(np.mean(np.sum(r**2, axis=1)))) for r in (before, after)]
    mx = [float(np.max(np.linalg.norm(r, axis=1))) for r in (before, after)]
    return doc.Holdout(
        log=loaded.log, artefact=loaded.artefact_file, centres=len(loaded.placement.centres),
        rms_before_um=rms[0], rms_after_um=rms[1], max_before_um=mx[0], max_after_um=mx[1],
        explained_fraction_rms=float(1.0 - (rms[1] / rms[0]) ** 2) if rms[0] > 0 else 0.0,
        method=("the held-out placement's ball setup fitted, everything else fixed: before = "
                "links and probe of the same placements fitted without a map (today's "
                "model), after = with the map; RMS and max of the centre residual magnitudes"))


def run_map(machine_path: Path | str, inputs: Sequence[tuple[str, str]],
            holdout: tuple[str, str] | None = None, *, stylus_radius_mm: float,
            fixed_radius: bool = False, repeatability_um: Sequence[float] | None = None,
            options: MapOptions | None = None, limit: Limit | None = None,
            limit_source: str | None = None, coverage_k: float = 2.0) -> MapRun:
    """Fit the map of ``inputs`` (probing log, artefact file) and build its document."""
    machine, mfile = load_machine(machine_path)
    return fit_map_placements(machine, mfile, str(machine_path), inputs, holdout,
                              stylus_radius_mm=stylus_radius_mm, fixed_radius=fixed_radius,
                              repeatability_um=repeatability_um, options=options, limit=limit,
                              limit_source=limit_source, coverage_k=coverage_k)


def fit_map_placements(machine: Machine, mfile: MachineFile, machine_label: str,
                       inputs: Sequence[tuple[str, str]],
                       holdout: tuple[str, str] | None = None, *, stylus_radius_mm: float,
                       fixed_radius: bool = False,
                       repeatability_um: Sequence[float] | None = None,
                       options: MapOptions | None = None, limit: Limit | None = None,
                       limit_source: str | None = None, coverage_k: float = 2.0) -> MapRun:
    """``run_map`` for a machine already loaded (the daemon's map job); ``machine_label``:
    the machine file (or entry) the document names."""
    options = options or MapOptions()
    loaded = [load_placement(machine, f"P{i + 1}", log, art, stylus_radius_mm, fixed_radius)
              for i, (log, art) in enumerate(inputs)]
    opts = MapOptions(options.max_degree, options.degrees, options.prior_um, options.prior_urad,
                      repeatability_um, options.visit_scatter, mfile.rotary_repeatability_urad)
    placements = [ld.placement for ld in loaded]
    est = fit_map(machine, placements, opts)
    model = model_of(machine, est)
    k = expanded_k(est.sigma_dof, coverage_k) if np.isfinite(est.sigma_dof) else coverage_k
    ho = None
    if holdout is not None:
        hl = load_placement(machine, "holdout", holdout[0], holdout[1], stylus_radius_mm,
                            fixed_radius)
        base = fit_map(machine, placements, MapOptions(
            degrees={"X": 0, "Y": 0, "Z": 0}, sigma_um=repeatability_um, visit_scatter=False))
        ho = _holdout(machine, hl, est, base)
    document = _document(machine, Path(machine_label), loaded, est, model,
                         _figures(model, limit, limit_source, k), ho, opts)
    return MapRun(document, model, est, machine)


def _document(machine: Machine, machine_path: Path, loaded: list[_Loaded], est: MapEstimate,
              model: MapModel, figures: doc.Figures, ho: doc.Holdout | None,
              opts: MapOptions) -> doc.LinearMapFile:
    n = est.layout.n_model
    names = est.names
    placements = []
    for i, ld in enumerate(loaded):
        s = est.layout.ball_slice(i)
        v, u = est.p[s].reshape(-1, 3) * 1e3, est.std[s].reshape(-1, 3) * 1e3
        res = est.residual_mm[i] * 1e3
        xyz = ld.placement.centres.xyz_mm
        placements.append(doc.Placement(
            name=ld.placement.name, log=ld.log, artefact=ld.artefact_file, run_id=ld.run_id,
            centres=len(xyz), poses=len(set(ld.placement.centres.pose.tolist())),
            residual_rms_um=float(np.sqrt(np.mean(res**2))),
            balls_um={b: {"value": [float(a) for a in v[j]], "std": [float(a) for a in u[j]]}
                      for j, b in enumerate(ld.placement.artefact.ids)},
            covered_mm={a: [float(xyz[:, j].min()), float(xyz[:, j].max())]
                        for j, a in enumerate("XYZ")}))
    obs = est.observability
    degrees = est.order.degrees if est.order else (dict(opts.degrees) if opts.degrees else {})
    tip = est.layout.tip_slice
    sd = est.sigma_dof
    order = None
    if est.order is not None:
        best = sorted(est.order.scores.items(), key=lambda kv: kv[1])[:10]
        order = doc.OrderChoice(method=est.order.method, max_degree=opts.max_degree,
                                degrees=est.order.degrees,
                                best=[{"degrees": list(c), "heldout_rms": s} for c, s in best])
    side = ", ".join(a for a in machine.tool_chain if a in "XYZ")
    box = ", ".join(f"{a} {lo:g}..{hi:g}" for a, (lo, hi) in model.box_mm.items())
    note = (f"The map is known over the covered box only ({box} mm): predictions outside it "
            "are refused. "
            f"With one stylus (tool tip {list(machine.tool_tip_mm)} mm in the tool frame), an "
            f"angular error of a tool-side axis ({side}) that moves the tip as a straightness "
            "does is held by that straightness: the map is valid for this stylus.")
    return doc.LinearMapFile(
        schema_=doc.SCHEMA,
        created_utc=datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        machine={"name": machine.name, "topology": machine.topology,
                 "file": str(machine_path), "tool_tip_mm": list(machine.tool_tip_mm)},
        placements=placements,
        basis=doc.Basis(
            argument=("u = (2x − lo − hi)/(hi − lo), x the axis' controller position (mm) over "
                      "its covered range [lo, hi]; e(x) = Σ_k c_k P_k(u), Legendre P_k, k ≥ 1"),
            axes=[doc.AxisBasis(axis=a, range_mm=list(model.box_mm[a]),
                                degree=int(degrees.get(a, 0)), sign=machine.axes[a].sign)
                  for a in "XYZ"]),
        functions=_functions(machine, est, model),
        links={k: doc.Value(value=v, std=u, unit=unit)
               for k, (v, u, unit) in est.links_si().items()},
        probe_um={"value": [float(a) for a in est.p[tip] * 1e3],
                  "std": [float(a) for a in est.std[tip] * 1e3]},
        parameters=doc.Parameters(names=names[:n], values=[float(a) for a in est.p[:n]],
                                  covariance=est.cov[:n, :n].tolist()),
        observability=doc.Observability(
            scale_observable=obs.scale_observable,
            unobservable=obs.statement(machine, degrees or None),
            kept_terms=list(est.basis.names), note=note),
        order=order,
        fit=doc.Fit(residual_rms_um=est.residual_rms_um, sigma_um=list(est.sigma_um),
                    sigma_from="given" if est.sigma_given else "a posteriori, per axis",
                    sigma_dof=None if not np.isfinite(sd) else float(sd),
                    iterations=est.iterations, converged=est.converged,
                    condition_number=est.condition_number,
                    prior={"translation_um": est.prior_um, "rotation_urad": est.prior_urad,
                           "applies_to": "every map coefficient, N(0, τ²) per Legendre term"},
                    visit_scatter=None if est.visit_scatter is None else {
                        k: list(v) for k, v in est.visit_scatter.items()},
                    refit=REFIT),
        rigid_convention=RIGID, figures=figures, holdout=ho,
        warnings=[w for ld in loaded for w in ld.warnings] + est.warnings)
