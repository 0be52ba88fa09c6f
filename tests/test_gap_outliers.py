"""The gap diagnosis with a faulty ball visit: a robust floor, the visit left out and
named as the verdict ``measurement_outlier``; and the report's "gap at" lines: the significant
ones above the floor, then a count."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from benchmarks.rigs.gap_helpers import CONFIG, STYLUS_R, annex_b_setup, gap_truth
from contracts.probing_log import read_log, write_log
from daemon.cli.main import main
from identification.effects import make_effect
from identification.gap import diagnose
from identification.gap.locate import MAX_SHOWN, shown_locations
from identification.gap.simlog import simulate

EXAMPLE = CONFIG / "examples/thesis_annexB_14poses.csv"


@pytest.fixture(scope="module")
def setup():
    return annex_b_setup()


def _chip(data, pose: int, ball: int, touch: int, um: float) -> None:
    """That touch latched ``um`` outside the ball (against its approach), as a chip does."""
    k = np.flatnonzero((data.pose == pose) & (data.ball == ball) & (data.touch == touch))[0]
    data.xyz_mm[k] -= um * 1e-3 * data.direction[k]


@pytest.mark.parametrize(("touch", "stage"), [(3, "sphere"), (5, "centre")])
def test_a_chip_is_its_own_verdict_and_leaves_the_floor_alone(setup, touch, stage):
    machine, artefact, poses = setup
    data = simulate(machine, artefact, poses, gap_truth(artefact, 1), STYLUS_R, 0.5, seed=4)
    clean = diagnose(machine, artefact, data, STYLUS_R)
    assert clean["verdict"]["effect"] == "none" and clean["outliers"] == []
    _chip(data, 6, 2, touch, 15.0)
    rep = diagnose(machine, artefact, data, STYLUS_R)
    v = rep["verdict"]
    assert v["effect"] == "measurement_outlier"
    (o,) = rep["outliers"]
    assert (o["pose"], o["ball"], o["touch"], o["stage"], o["log"]) == (6, "B3", touch, stage,
                                                                        "train")
    assert o["size_um"] == pytest.approx(15.0, abs=1.5)
    assert f"ball B3 pose 6 touch {touch} (+1" in v["message"]
    assert v["without_outliers"]["effect"] == "none"  # the rest: nothing invented
    assert rep["twin"]["groups_train"] == 14 * 4 - 1
    # the floor is the clean run's: one bad visit does not inflate it
    assert rep["noise_floor_um"] == pytest.approx(clean["noise_floor_um"], rel=0.05)
    json.dumps(rep)


def test_a_real_effect_is_still_found_beside_a_chip(setup):
    machine, artefact, poses = setup
    drift = make_effect("thermal_drift", "Y", machine)
    truth = gap_truth(artefact, 2, effects=[(drift, np.array([6.0]))])
    data = simulate(machine, artefact, poses, truth, STYLUS_R, 0.5, seed=5)
    _chip(data, 9, 0, 1, 20.0)
    rep = diagnose(machine, artefact, data, STYLUS_R)
    assert rep["verdict"]["effect"] == "measurement_outlier"
    assert [(o["pose"], o["ball"], o["touch"]) for o in rep["outliers"]] == [(9, "B1", 1)]
    rest = rep["verdict"]["without_outliers"]
    assert (rest["effect"], rest["axis"]) == ("thermal_drift", "Y")


def test_only_significant_locations_above_the_floor_are_listed():
    cells = [{"by": "pose", "key": f"p{i}", "rms_um": 1.0, "ratio_to_floor": 5.0 - 0.2 * i,
              "n": 4, "p_value": 1e-6} for i in range(14)]
    cells += [{"by": "direction", "key": "touch 1", "rms_um": 0.1, "ratio_to_floor": 0.6,
               "n": 56, "p_value": 1e-5}]
    brk = [dict(c, significant=True) for c in cells]
    shown, more, below = shown_locations(cells, brk)
    assert [c["key"] for c in shown] == [f"p{i}" for i in range(MAX_SHOWN)]
    assert (more, below) == (14 - MAX_SHOWN, 1) and all(c["significant"] for c in shown)
    brk[0]["significant"] = False  # a hint cell (the gap is significant, no cell alone)
    assert "p0" not in [c["key"] for c in shown_locations(cells, brk)[0]]
    shown, _, _ = shown_locations(cells, brk, limit=20)  # after every significant one
    assert shown[-1]["key"] == "p0" and not shown[-1]["significant"]


def test_gap_cli_names_the_visit_and_counts_the_other_locations(setup, tmp_path, capsys):
    _, artefact, _ = setup
    rows = list(read_log(EXAMPLE, artefact))
    k = next(i for i, r in enumerate(rows) if (r.pose, r.ball, r.touch) == (4, "B2", 4))
    r = rows[k]
    d = np.array([r.dir_x, r.dir_y, r.dir_z]) * 0.012  # a 12 µm chip
    rows[k] = replace(r, x_mm=r.x_mm - d[0], y_mm=r.y_mm - d[1], z_mm=r.z_mm - d[2])
    log = tmp_path / "chip.csv"
    write_log(log, rows)
    html = tmp_path / "gap.html"
    assert main(["gap", "--log", str(log), "--machine",
                 str(CONFIG / "machines/thesis_wcbxfzyt.yaml"), "--artefact",
                 str(CONFIG / "artefacts/thesis_4ball.yaml"), "--html", str(html),
                 "--no-visit-scatter"]) == 0  # the floor without visit scatter: many cells
    out = capsys.readouterr().out
    assert "measurement outlier: ball B2 pose 4 touch 4 (+1" in out  # +11.5 µm here
    assert "verdict: measurement_outlier" in out
    lines = [ln for ln in out.splitlines() if ln.startswith("  gap at ")]
    assert len(lines) == MAX_SHOWN  # this log has 36 cells, 32 of them significant
    assert "  … 22 more above the floor and 4 below it" in out
    page = html.read_text()
    assert "Measurement outliers (left out)" in page and "22 more above the floor" in page
