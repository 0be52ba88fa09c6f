"""Structure along a linear axis is found and located, not absorbed into the visit-scatter floor.

A cyclic (pitch) error and a local bump of a linear axis are functions of the axis position: the
per-visit scatter components estimated from the same run took them up as random centre scatter
and the run read ``none``. Each case runs end to end through `rumba gap` on the shipped hold-out
plan (seven estimate poses, the seven validate poses as a separate log).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from benchmarks.rigs.gap_helpers import (
    ARTEFACT,
    CONFIG,
    MACHINE,
    STYLUS_R,
    annex_b_setup,
    gap_truth,
    log_rows,
)
from contracts.probing_log import write_log
from contracts.setup_files import load_plan
from daemon.cli.main import main
from identification.effects import make_effect
from identification.gap.simlog import simulate


@pytest.fixture(scope="module")
def setup():
    machine, artefact, _ = annex_b_setup()
    plan = load_plan(CONFIG / "plans/shift_holdout_14poses.yaml")
    est = [(p.b_deg, p.c_deg) for p in plan.poses if p.role == "estimate"]
    val = [(p.b_deg, p.c_deg) for p in plan.poses if p.role == "validate"]
    return machine, artefact, est, val


def _gap(setup, tmp_path, truth, seed: int, *extra: str) -> dict:
    """`rumba gap --log … --holdout …` on the two simulated logs; the JSON report."""
    machine, artefact, est, val = setup
    logs = []
    for k, poses in enumerate((est, val)):
        data = simulate(machine, artefact, poses, truth, STYLUS_R, 0.5, seed=seed + k)
        logs.append(tmp_path / f"log{k}.csv")
        write_log(logs[-1], log_rows(data, artefact, run=f"r{k}"))
    out = tmp_path / "gap.json"
    assert main(["gap", "--log", str(logs[0]), "--holdout", str(logs[1]), "--machine",
                 str(MACHINE), "--artefact", str(ARTEFACT), "--json", str(out),
                 *extra]) == 0
    return json.loads(out.read_text())


def _honest_floor(rep: dict) -> None:
    """The floor holds the trigger noise and the rigid index scatter, nothing else."""
    parts = rep["noise"]["parts"]
    assert parts["ball_visit_um"] == 0.0
    assert rep["noise_floor_um"] ** 2 == pytest.approx(parts["trigger_um"] ** 2
                                                       + parts["index_um"] ** 2, rel=1e-3)
    assert rep["scatter"]["withheld"].startswith("structure along")


def test_pitch_error_of_x_is_located_not_read_none(setup, tmp_path, capsys):
    # 3.6 µm, 40 mm period along X. Before: `none`, the centre scatter per ball visit (z:
    # 1.9 µm — the pitch error's local slope moves the fitted radius, hence z) took it up
    # and the floor came out at 2.2 × the trigger noise
    machine, artefact, _, _ = setup
    eff = make_effect("cyclic_error", "X", machine, period_mm=40.0)
    truth = gap_truth(artefact, seed=1, effects=[(eff, np.array([3.0, 2.0]))])
    rep = _gap(setup, tmp_path, truth, 7920, "--html", str(tmp_path / "gap.html"))
    assert rep["verdict"]["effect"] == "unexplained", rep["verdict"]["message"]
    st = rep["structure"]
    assert st["found"] and st["axis"] == "X" and st["p_value"] < 0.01
    assert st["axes"]["Y"]["p_value"] > 0.01 and st["axes"]["Z"]["p_value"] > 0.01
    loc = st["located"]
    assert loc["shape"] == "cyclic" and abs(loc["period_mm"] - 40.0) < 4.0
    assert 1.0 < loc["size_um"] < 6.0
    _honest_floor(rep)
    assert "structure along X that no library effect explains: cyclic, period ≈" in \
        rep["verdict"]["message"]
    out = capsys.readouterr().out
    assert "STRUCTURE: structure along X: cyclic" in out
    assert "centre scatter per ball visit 0.000 µm (not credited: structure along X" in out
    page = (tmp_path / "gap.html").read_text()
    assert "What the floor is made of" in page and "Structure along the linear axes" in page
    assert page.count("data:image/png;base64,") >= 4  # the residuals along X plotted too


def test_local_bump_of_y_under_index_scatter_is_located(setup, tmp_path):
    # A 6 µm straightness bump (along Z) over 50 mm of Y, under 5 µrad B/C index scatter
    machine, artefact, _, _ = setup
    eff = make_effect("local_bump", "Y", machine, centre_mm=-40.0, width_mm=50.0,
                      component="EZY")
    truth = gap_truth(artefact, seed=4, effects=[(eff, np.array([6.0]))],
                      index_std_urad={"B": 5.0, "C": 5.0})
    rep = _gap(setup, tmp_path, truth, 104)
    assert rep["verdict"]["effect"] == "unexplained", rep["verdict"]["message"]
    st = rep["structure"]
    assert st["found"] and st["axis"] == "Y"
    loc = st["located"]
    assert loc["shape"] == "local" and loc["channel"] == "z"
    assert abs(loc["centre_mm"] - (-40.0)) < 25.0 and 15.0 < loc["width_mm"] < 100.0
    _honest_floor(rep)


def test_null_run_with_index_scatter_stays_none_and_credits_the_scatter(setup, tmp_path,
                                                                       capsys):
    # 10 µrad B/C index scatter and nothing else: no structure, the floor holds the scatter
    _, artefact, _, _ = setup
    truth = gap_truth(artefact, seed=2, index_std_urad={"B": 10.0, "C": 10.0})
    rep = _gap(setup, tmp_path, truth, 3)
    assert rep["verdict"]["effect"] == "none", rep["verdict"]["message"]
    st = rep["structure"]
    assert not st["found"] and st["p_value"] >= 0.01 and "located" not in st
    parts = rep["noise"]["parts"]
    assert parts["index_um"] > parts["trigger_um"] > 0.2
    assert rep["scatter"]["withheld"] is None
    assert "floor " in capsys.readouterr().out


def test_the_structure_test_holds_its_level_under_centre_scatter(setup):
    # The independent centre scatter per ball visit of a real probe (thesis §3.4) is random
    # from ball to ball: no structure, and the floor keeps it (the shipped example log, made
    # so, reads `none`: tests/test_gap_step.py)
    from identification.gap import diagnose

    machine, artefact, est, val = setup
    truth = gap_truth(artefact, seed=5)
    rng = np.random.default_rng(11)
    data = [simulate(machine, artefact, p, truth, STYLUS_R, 0.3, seed=50 + k)
            for k, p in enumerate((est, val))]
    for d in data:  # 0.96 µm per ball visit along y (thesis §3.4), the same for its touches
        visit = d.pose * 10 + d.ball
        shift = rng.normal(0, 0.96e-3, visit.max() + 1)
        d.xyz_mm[:, 1] += shift[visit]
    rep = diagnose(machine, artefact, data[0], STYLUS_R, holdout=data[1])
    assert rep["verdict"]["effect"] == "none" and not rep["structure"]["found"]
    assert rep["noise"]["parts"]["ball_visit_um"] > 0.2


@pytest.mark.parametrize("scenario,axis", [("cyclic_error", "Z"), ("local_bump+scatter", "X")])
def test_selfcheck_holds_the_linear_axis_errors(scenario, axis):
    # rumba gap --selfcheck: a cyclic error and a local bump of each linear axis, with and
    # without index scatter, at a machine's sizes: never `none`, located along their axis
    from identification.gap import selfcheck

    machine, artefact, poses = annex_b_setup()
    assert selfcheck.axes_of(scenario, machine, artefact) == ["X", "Y", "Z"]
    case = selfcheck.run_case(machine, artefact, poses, STYLUS_R, scenario, axis, 17)
    assert case.ok and case.located and case.verdict != "none", case


def test_a_pole_chip_below_the_outlier_test_is_no_structure(monkeypatch):
    # One visit's gross residual — a chip on the pole that the outlier test cannot name under
    # the scatter — moves one centre by several µm: a narrow local "shape" of any axis fits it.
    # The test counts only what different visits agree on (and winsorises): before it did,
    # this self-check case read "structure along Y: local, ≈ 6.3 µm" and the floor dropped
    from identification.gap import selfcheck

    reports = []
    real = selfcheck.diagnose
    monkeypatch.setattr(selfcheck, "diagnose", lambda *a, **k: reports.append(real(*a, **k))
                        or reports[-1])
    machine, artefact, poses = annex_b_setup()
    case = selfcheck.run_case(machine, artefact, poses, STYLUS_R, "pole_chip+scatter", None,
                              1017)
    assert case.ok and case.verdict == "none", case
    assert not reports[-1]["structure"]["found"] and not reports[-1]["outliers"]


def test_a_library_effect_over_structure_gets_no_centre_scatter_in_its_floor(setup):
    # A 5 µm bump (along Z) over 40 mm near the end of X, under 5 µrad index scatter: the
    # twin's residuals show structure along X and a straightness of X takes it. Before, the
    # pass with the straightness fixed found no structure left and credited a centre scatter
    # per ball visit again (0.23 µm): the floor rose to 1.5× the trigger noise to meet the
    # gap the straightness leaves. Now the floor is the trigger noise and the rigid index
    # scatter, and the straightness is named only because its gap comes down to that
    from identification.gap import diagnose

    machine, artefact, est, val = setup
    eff = make_effect("local_bump", "X", machine, centre_mm=155.0, width_mm=40.0,
                      component="EZX")
    truth = gap_truth(artefact, seed=5, effects=[(eff, np.array([5.0]))],
                      index_std_urad={"B": 5.0, "C": 5.0})
    data = [simulate(machine, artefact, p, truth, STYLUS_R, 0.5, seed=500 + k)
            for k, p in enumerate((est, val))]
    rep = diagnose(machine, artefact, data[0], STYLUS_R, holdout=data[1])
    assert rep["structure"]["found"] and rep["structure"]["axis"] == "X"
    v = rep["verdict"]
    assert (v["effect"], v["axis"]) in {("straightness", "X"), ("unexplained", None)}, v
    _honest_floor(rep)
    assert v["holdout_rms_after_um"] <= 1.5 * rep["noise_floor_um"] or \
        v["effect"] == "unexplained"


def test_a_later_pass_keeps_the_first_passs_structure_finding(setup):
    # A run of the acceptance Monte Carlo (bump, shift-14, run 47: a bump read as a
    # straightness of Z): the pass re-estimating the components with the straightness fitted
    # saw the structure at p = 0.012, no longer below α, and credited 0.19 µm of centre
    # scatter per ball visit again. The first pass found structure: no pass credits it.
    from benchmarks.bench_structure import _plans, run_one

    machine, artefact, _, _ = setup
    r = run_one("bump", "shift-14", 47, machine, artefact, _plans())
    assert (r["verdict"], r["verdict_axis"]) == ("straightness", "Z"), r
    assert r["floor_parts"]["ball_visit_um"] == 0.0, r  # 0.19 µm before
