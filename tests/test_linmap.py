"""The map of the linear axes (identification/linmap): analytic Jacobian columns against finite
differences, a noiseless map recovered, the observability statement derived from the data, the
spheres re-fitted in the estimate's frame, and predictions that refuse to extrapolate."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from contracts.setup_files import load_artefact, load_machine
from identification.identifiability import identifiable_links, nominal_centres
from identification.linmap.field import (
    MapModel,
    OutsideCoverage,
    compare_maps,
    predict_field,
    raw_field,
    remove_best_rigid,
)
from identification.linmap.fit import MapOptions, fit_map
from identification.linmap.observe import observable_terms
from identification.linmap.problem import JointLayout, Placement, covered_ranges, evaluate
from identification.linmap.terms import MapBasis, candidate_terms
from simulators.exact_log import THESIS_LINKS_UM_URAD, to_internal
from tests.map_helpers import map_truth, moved, placement, with_true_distance

ROOT = Path(__file__).resolve().parent.parent
CFG = ROOT / "config"
POSES = [(b, c) for b in (-45.0, -15.0, 15.0, 45.0) for c in range(0, 360, 60)]


def machine(name: str):
    return load_machine(CFG / "machines" / f"{name}.yaml")[0]


ARTEFACT = load_artefact(CFG / "artefacts" / "thesis_4ball.yaml")


def _layout(m, pls, degree=3, links=4):
    basis = MapBasis(covered_ranges(m, pls), tuple(candidate_terms("XYZ", degree)))
    return JointLayout(tuple(m.location_error_names()[:links]), basis,
                       tuple(len(p.artefact.balls) for p in pls))


@pytest.mark.parametrize("name", ["thesis_wcbxfzyt", "swivelhead_wcfxyzbt"])
@pytest.mark.parametrize("with_map", [False, True])
def test_jacobian_columns_match_finite_differences(name, with_map):
    """d(centre)/dp of every parameter — links, map coefficients, probe, balls of two
    placements — against central differences. At a zero map dg/dq is exact and they agree to
    1e-5 of the column (the difference's own error); with µm-size motion errors the chain's
    dg/dq is the unit-step chord model.predict uses, 1e-4."""
    m = machine(name)
    c = nominal_centres(m, ARTEFACT, POSES[::4])
    art2 = moved(ARTEFACT, (30.0, -20.0, 60.0))
    pls = [Placement("a", ARTEFACT, c), Placement("b", art2, nominal_centres(m, art2, POSES[1::4]))]
    lay = _layout(m, pls, degree=2)
    rng = np.random.default_rng(3)
    p = np.zeros(lay.size)
    p[: len(lay.links)] = rng.normal(0, 2e-5, len(lay.links))
    if with_map:
        p[lay.map_slice] = [rng.normal(0, 2e-5 if t.rotation else 0.01) for t in lay.basis.terms]
    p[lay.tip_slice.start:] = rng.normal(0, 0.2, lay.size - lay.tip_slice.start)
    ev = evaluate(m, pls, lay, p, jacobian=True)
    for k in range(lay.size):
        h = 1e-7 if k < len(lay.links) or (
            lay.map_slice.start <= k < lay.map_slice.stop
            and lay.basis.terms[k - lay.map_slice.start].rotation) else 1e-5
        pp, pm = p.copy(), p.copy()
        pp[k] += h
        pm[k] -= h
        a, b = evaluate(m, pls, lay, pp), evaluate(m, pls, lay, pm)
        for i in range(2):
            fd = (a.pred[i] - b.pred[i]) / (2 * h)
            scale = max(np.max(np.abs(fd)), 1e-3)
            err = np.max(np.abs(fd - ev.jac[i][:, :, k])) / scale
            assert err < (1e-4 if with_map else 1e-5), (lay.names(pls)[k], i, err)


def test_the_field_jacobian_matches_finite_differences():
    m = machine("thesis_wcbxfzyt")
    pls = [Placement("a", ARTEFACT, nominal_centres(m, ARTEFACT, POSES))]
    lay = _layout(m, pls, links=8)
    rng = np.random.default_rng(5)
    v = np.concatenate([rng.normal(0, 2e-5, len(lay.links)),
                        [rng.normal(0, 2e-5 if t.rotation else 0.01) for t in lay.basis.terms]])
    box = {"X": (-100.0, 100.0), "Y": (-80.0, 80.0), "Z": (0.0, 150.0)}
    model = MapModel(m, lay.links, lay.basis, v, np.eye(len(v)), box)
    pts = model.grid(3)
    _, jac, _ = raw_field(model, pts, jacobian=True)
    for k in range(len(v)):
        h = 1e-7 if k < len(lay.links) or lay.basis.terms[k - len(lay.links)].rotation else 1e-5
        vp, vm = v.copy(), v.copy()
        vp[k] += h
        vm[k] -= h
        fd = (raw_field(model, pts, vp)[0] - raw_field(model, pts, vm)[0]) / (2 * h)
        assert np.max(np.abs(fd - jac[:, :, k])) < 1e-6 * max(np.max(np.abs(fd)), 1.0), k


@pytest.fixture(scope="module")
def thesis_maps():
    """The thesis machine (Table B.2 links, a degree-3 random smooth map over more than the
    covered box), the 4-ball artefact at its place (with its true calibrated distance) and
    moved out and up: 24 poses each, exact touches, no noise."""
    m = machine("thesis_wcbxfzyt")
    truth = map_truth(m, seed=7, order=3, links=to_internal(THESIS_LINKS_UM_URAD),
                      ranges_mm={"X": [-400, 400], "Y": [-300, 300], "Z": [-100, 400]})
    rng = np.random.default_rng(1)
    b1, b2 = rng.normal(0, 0.2, (4, 3)), rng.normal(0, 0.2, (4, 3))
    a1 = with_true_distance(ARTEFACT, b1)
    a2 = moved(ARTEFACT, (40.0, -30.0, 120.0), 1.4)
    p1, _, q1 = placement(truth, "P1", a1, POSES, b1)
    p2, _, q2 = placement(truth, "P2", a2, POSES, b2)
    return m, truth, (p1, p2), (q1, q2)


def _field_error(m, truth, est, n=200):
    from daemon.analysis.linear_map import model_of

    model = model_of(m, est)
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(*model.box_mm[a], n) for a in "XYZ"])
    pred = predict_field(model, pts)
    _, _, pw = raw_field(model, pts)
    d = remove_best_rigid(pred.error_um * 1e-3 - truth.field_mm(pts), pw) * 1e3
    truth_um = remove_best_rigid(truth.field_mm(pts), pw) * 1e3
    return np.sqrt(np.mean(np.sum(d**2, 1))), np.sqrt(np.mean(np.sum(truth_um**2, 1))), pred


def test_a_noiseless_map_is_recovered(thesis_maps):
    """Exact touches on a degree-3 truth, degrees fixed at 3: the volumetric field at 200
    points inside the covered box within 0.02 µm RMS of the truth (measured 0.001 µm; the
    truth's is 11 µm) and the centres fitted to 0.01 µm. (The links are not compared: the
    constant part of each angular error over the covered range is a link, EBX's is EB0C.)"""
    m, truth, pls, _ = thesis_maps
    est = fit_map(m, list(pls), MapOptions(degrees={"X": 3, "Y": 3, "Z": 3},
                                           visit_scatter=False))
    diff, size, _ = _field_error(m, truth, est)
    assert size > 5.0 and diff < 0.02, (diff, size)
    assert est.residual_rms_um < 0.01


def test_the_controller_frame_sphere_is_biased_and_the_refit_is_not(thesis_maps):
    """The five touches fitted in controller coordinates miss the true centre by up to tenths
    of a µm under this map's slopes; the map fitted with its touches re-fits them in its own
    frame: the same map from spheres as from exact centres (field within 0.02 µm), while the
    map from the controller-frame spheres alone is off by more (> 0.05 µm)."""
    m, truth, pls, exact = thesis_maps
    bias = max(np.max(np.abs(p.centres.xyz_mm - q)) for p, q in zip(pls, exact, strict=True))
    assert bias * 1e3 > 0.05, bias
    opts = MapOptions(degrees={"X": 3, "Y": 3, "Z": 3}, visit_scatter=False)
    bare = [Placement(p.name, p.artefact, p.centres) for p in pls]
    d_bare, _, _ = _field_error(m, truth, fit_map(m, bare, opts))
    d_refit, _, _ = _field_error(m, truth, fit_map(m, list(pls), opts))
    assert d_refit < 0.02 < 0.05 < d_bare, (d_refit, d_bare)


def test_observability_names_scale_squareness_and_the_stylus():
    """Derived, not listed: on the thesis machine (tool tip at Y's reference point) without a
    calibrated distance the isotropic scale is named and Z's positioning slope dropped for it;
    each linear straightness is a squareness (a link); every angular error of Y — the tool
    side — moves the tip only as Y's straightness does, and the statement says the map holds
    their sum for this stylus. The links kept are today's eight (identifiability). With the
    calibrated distance the scale is observable and EZZ_P1 kept. On the swivel head, whose B
    tilts the 370 mm stylus arm, Z's angular errors are observable and kept."""
    m = machine("thesis_wcbxfzyt")
    c = nominal_centres(m, ARTEFACT, POSES)
    pls = [Placement("P1", ARTEFACT, c)]
    ranges = covered_ranges(m, pls)
    obs = observable_terms(m, pls, candidate_terms("XYZ", 3), ranges)
    assert obs.links == identifiable_links(m, ARTEFACT, c).links
    said = obs.statement(m)
    assert not obs.scale_observable and "isotropic_scale" in said
    assert "isotropic scale" in said["EZZ_P1"]
    for straight, link in (("EXY_P1", "EC0Y"), ("EZY_P1", "EA0Y"), ("EXZ_P1", "EB0Z")):
        assert link in said[straight] and "squareness" in said[straight]
    for comp in ("EAY", "EBY", "ECY"):
        assert "valid for this stylus" in said[comp] and "every degree (3)" in said[comp]
    kept = {t.name for t in obs.terms}
    assert {"EXX_P1", "EYY_P1", "EAX_P2", "EAZ_P2", "ECZ_P2"} <= kept
    scaled = load_artefact(CFG / "artefacts" / "thesis_4ball_scaled.yaml")
    obs2 = observable_terms(m, [Placement("P1", scaled, c)], candidate_terms("XYZ", 3), ranges)
    assert obs2.scale_observable and "EZZ_P1" in {t.name for t in obs2.terms}
    assert "isotropic_scale" not in obs2.statement(m)
    sw = machine("swivelhead_wcfxyzbt")
    vert = load_artefact(CFG / "artefacts" / "vertical_4ball.yaml")
    poses = [(b, c) for b in (-30.0, -10.0, 10.0, 30.0) for c in range(0, 360, 60)]
    c3 = nominal_centres(sw, vert, poses)
    pl3 = [Placement("P1", vert, c3)]
    obs3 = observable_terms(sw, pl3, candidate_terms("XYZ", 2), covered_ranges(sw, pl3))
    assert {"EAZ_P1", "EBZ_P1", "EAZ_P2", "EBZ_P2"} <= {t.name for t in obs3.terms}


def test_predictions_refuse_points_outside_the_covered_box(thesis_maps):
    m, _, pls, _ = thesis_maps
    from daemon.analysis.linear_map import model_of

    est = fit_map(m, list(pls), MapOptions(degrees={"X": 2, "Y": 2, "Z": 2},
                                           visit_scatter=False))
    model = model_of(m, est)
    hi = model.box_mm["Y"][1]
    inside = np.array([[np.mean(model.box_mm["X"]), hi, np.mean(model.box_mm["Z"])]])
    assert predict_field(model, inside).error_um.shape == (1, 3)
    with pytest.raises(OutsideCoverage, match=r"point 2: Y = .* outside the covered range"):
        predict_field(model, np.vstack([inside, inside + np.array([0.0, 0.01, 0.0])]))


def test_compare_maps_removes_the_rigid_motion_of_their_difference(thesis_maps):
    """A map against itself with a rigid translation and rotation of its workpiece (the links
    EX0C and EB0C at rotary zero): 0; against the map of other data: the size of their
    difference."""
    m, _, pls, _ = thesis_maps
    from daemon.analysis.linear_map import model_of

    est = fit_map(m, list(pls), MapOptions(degrees={"X": 2, "Y": 2, "Z": 2},
                                           visit_scatter=False))
    a = model_of(m, est)
    v = a.values.copy()
    v[list(a.links).index("EX0C")] += 0.005
    v[list(a.links).index("EB0C")] += 3e-5
    b = MapModel(m, a.links, a.basis, v, a.cov, a.box_mm)
    same = compare_maps(a, b)
    assert same["max_um"] < 0.005, same  # second order: 30 µrad × 5 µm
    c = MapModel(m, a.links, a.basis, a.values * 0.5, a.cov, a.box_mm)
    assert compare_maps(a, c)["rms_um"] > 1.0
