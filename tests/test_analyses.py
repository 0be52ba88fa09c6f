"""Analyses: Table 4.2 cluster behaviour, validation (annex B), distances, sign conventions."""

from pathlib import Path

import numpy as np
import pytest

from contracts.setup_files import load_artefact, load_machine, load_plan
from daemon.analysis.touch_centres import rows_to_centres
from identification.analyses import (
    cluster_fit,
    clusters,
    distance_analysis,
    estimate_and_validate,
    volumetric,
)
from identification.estimate import estimate
from identification.model import predict
from simulators.exact_log import THESIS_LINKS_UM_URAD, Truth, make_rows, to_internal

CFG = Path(__file__).resolve().parents[1] / "config"
PLAN = load_plan(CFG / "plans/thesis_annexB_14poses.yaml")
POSES = [(p.b_deg, p.c_deg) for p in PLAN.poses]
B30_C60 = POSES.index((30.0, 60.0))
SETUP = np.random.default_rng(11).uniform(-0.3, 0.3, (4, 3))
TIP = np.array([0.2, -0.1, 0.25])


@pytest.fixture(scope="module")
def thesis():
    m, _ = load_machine(CFG / "machines/thesis_wcbxfzyt.yaml")
    return m, load_artefact(CFG / "artefacts/thesis_4ball.yaml")


def _cluster_at_b30_c60(m, a, links_um_urad):
    truth = Truth(to_internal(links_um_urad), SETUP, TIP)
    c = rows_to_centres(make_rows(m, a, POSES, truth), a, 3.0).centres
    e = estimate(m, a, c)  # setup + links simultaneously, then setup-only prediction (§4.5)
    vol = volumetric(m, a, e, c)
    pred, _ = predict(m, a, e.layout, e.setup_only(), c)
    return next(x for x in clusters(c, pred, vol.before_um, a.ids) if x.pose == B30_C60)


@pytest.mark.parametrize("name", ["EA0B", "EC0B", "EA0C", "EB0C"])
def test_table_4_2_rotary_orientation_is_pure_relocalisation(thesis, name: str) -> None:
    x = _cluster_at_b30_c60(*thesis, {name: 5.0})
    assert np.linalg.norm(x.angular_urad) == pytest.approx(5.0, abs=0.05)
    assert max(np.linalg.norm(v) for v in x.local_um.values()) < 0.05


def test_table_4_2_offset_cb_is_pure_translation(thesis) -> None:
    x = _cluster_at_b30_c60(*thesis, {"EX0C": 5.0})
    assert np.linalg.norm(x.linear_um) == pytest.approx(5.0, abs=0.05)
    # EX0C along x of B, seen after B = 30°: (cos 30°, 0, −sin 30°) · 5 µm.
    np.testing.assert_allclose(x.linear_um, [4.330, 0.0, -2.5], atol=1e-3)
    assert np.linalg.norm(x.angular_urad) < 1e-3
    assert max(np.linalg.norm(v) for v in x.local_um.values()) < 1e-3


@pytest.mark.parametrize("name", ["EB0Z", "EA0Y", "EC0Y"])
def test_table_4_2_squareness_gives_local_distortion(thesis, name: str) -> None:
    x = _cluster_at_b30_c60(*thesis, {name: 5.0})
    assert max(np.linalg.norm(v) for v in x.local_um.values()) > 0.1


def test_relocalisation_sign_is_predicted_to_measured() -> None:
    p = np.array([[100.0, 0, 0], [0, 100.0, 0], [0, 0, 100.0], [50.0, 50.0, 80.0]])
    d, r = np.array([3.0, -2.0, 1.0]), np.array([10.0, -20.0, 5.0])  # µm, µrad
    err = d + np.cross(r * 1e-6, p * 1e3)  # measured − predicted in µm
    x = cluster_fit(p, err, ["a", "b", "c", "d"])
    np.testing.assert_allclose(x.linear_um, d, atol=1e-9)
    np.testing.assert_allclose(x.angular_urad, r, atol=1e-9)
    assert max(np.abs(v).max() for v in x.local_um.values()) < 1e-9


def test_cluster_needs_three_non_collinear_balls() -> None:
    p = np.array([[0.0, 0, 0], [100.0, 0, 0], [200.0, 0, 0]])
    x = cluster_fit(p, np.ones((3, 3)), ["a", "b", "c"])
    assert x.linear_um is None and x.angular_urad is None and "collinear" in x.note


def test_annex_b_estimate_7_validate_7(thesis) -> None:
    m, a = thesis
    truth = Truth(to_internal(THESIS_LINKS_UM_URAD), SETUP, TIP)
    c = rows_to_centres(make_rows(m, a, POSES, truth, touch_noise_um=0.5, seed=3),
                        a, 3.0).centres
    _, val = estimate_and_validate(m, a, c, PLAN.indices("validate"))
    assert val.poses == PLAN.indices("validate")
    assert len(c.subset(~np.isin(c.pose, val.poses))) == 28
    # Thesis: 117 → 12 µm, 90 %. Here the data hold only the link errors and noise.
    assert 90.0 < val.max_before_um < 130.0
    assert val.max_after_um < 5.0
    assert val.explained_fraction > 0.9 and val.explained_fraction_rms > 0.9
    assert val.explained_fraction == pytest.approx(1 - val.max_after_um / val.max_before_um)


def test_volumetric_and_distances(thesis) -> None:
    m, a = thesis
    truth = Truth(to_internal({"EX0C": -100.0, "EB0Z": 20.0}), SETUP, TIP)
    c = rows_to_centres(make_rows(m, a, POSES, truth), a, 3.0).centres
    e = estimate(m, a, c)
    v = volumetric(m, a, e, c)
    assert v.max_before_um > 90.0 and v.max_after_um < 1e-5
    d = distance_analysis(c, a.ids)
    assert len(d) == 6 * len(POSES)
    for pair in {(x.ball_a, x.ball_b) for x in d}:
        devs = [x.deviation_um for x in d if (x.ball_a, x.ball_b) == pair]
        assert abs(np.mean(devs)) < 1e-9
    # The BC offset moves the cluster rigidly (no distance change); the squareness does not.
    assert max(abs(x.deviation_um) for x in d) > 0.5
    c2 = rows_to_centres(make_rows(m, a, POSES, Truth(to_internal({"EX0C": -100.0}), SETUP,
                                                          TIP)), a, 3.0).centres
    assert max(abs(x.deviation_um) for x in distance_analysis(c2, a.ids)) < 1e-6
