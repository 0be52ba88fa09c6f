"""Shorter moves: transit heights from the keep-out geometry never come closer than the margin
(property tests), the two-speed touch (safety, cycle time, LinuxCNC's interpreter, and the
simulator latching the slow re-touch with the slow speed's repeatability), the candidates the
optimiser refuses without building, and the run order of the chosen poses."""

from __future__ import annotations

import itertools
import shutil
import subprocess
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from contracts.setup_files import PoseFile, load_artefact, load_machine, load_plan
from programs.candidates import Candidates
from programs.design import build_design
from programs.geometry import ProgramError
from programs.heights import PoseHeights
from programs.optimise import candidate_poses
from programs.plan_order import monotone, order_tour, unwrap_c
from programs.safety import SafetyError, check_program
from programs.toolpath import build_program
from simulators.errors_schema import load_errors
from simulators.offline import run_sync
from simulators.truth import TruthModel
from tests.regen_golden import golden_setup

ROOT = Path(__file__).resolve().parent.parent
CONFIG = ROOT / "config"


# ------------------------------------------------------------------ heights from geometry

@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(st.floats(-100, 100), st.floats(-100, 100), st.floats(-50, 150),
                          st.floats(1, 40)), min_size=1, max_size=6),
       st.tuples(st.floats(-150, 150), st.floats(-150, 150)),
       st.tuples(st.floats(-150, 150), st.floats(-150, 150)),
       st.sampled_from([1.0, -1.0]))
def test_transit_height_keeps_every_sphere_clear(spheres, a, b, rate):
    """Any point of the rectangle a-b at the transit height is at least the clearance radius
    from every sphere centre (the margin is inside the radius)."""
    c = np.array(spheres, float)
    h = PoseHeights(2, rate, [0, 1], c[:, :2], c[:, 2] * rate, c[:, 3],
                    np.array([-1e4 * rate, 0.0, 0.0]), 0.0, 0.0, -1e4 * rate, [])
    z = h.transit(np.array(a), np.array(b))
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    g = np.stack(np.meshgrid(np.linspace(lo[0], hi[0], 41), np.linspace(lo[1], hi[1], 41)),
                 axis=-1).reshape(-1, 2)
    # nearest rectangle point to each centre too: the sampling cannot miss the critical one
    g = np.vstack([g, np.clip(c[:, :2], lo, hi)])
    up = (z - c[:, 2] * rate) * rate  # height above each centre along the spindle
    d = np.sqrt(((g[:, None, :] - c[None, :, :2]) ** 2).sum(-1) + up[None, :] ** 2)
    assert np.all(d >= c[None, :, 3] - 1e-6)


@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.floats(0.1, 12.0), st.floats(0.5, 3.0), st.sampled_from([(0, 0), (30, 60), (-45, 210),
                                                                    (15, 300)]))
def test_heights_never_come_below_the_safety_margin(clearance, standoff, pose):
    """Whatever clearance a plan asks (even below the standoff), the program the heights
    make passes the safety check: nothing comes closer than the standoff to a keep-out."""
    machine, mf = load_machine(CONFIG / "machines" / "thesis_wcbxfzyt.yaml")
    art = load_artefact(CONFIG / "artefacts" / "thesis_4ball.yaml")
    plan = load_plan(CONFIG / "plans" / "shift_start_14poses.yaml").model_copy(update={
        "poses": [PoseFile(b_deg=0, c_deg=0), PoseFile(b_deg=pose[0], c_deg=pose[1])],
        "clearance_mm": clearance, "standoff_mm": standoff, "drift_check": False})
    report = check_program(build_program(machine, mf, art, plan))  # raises when too close
    assert report.min_slack_mm >= -1e-6  # slack beyond the standoff, to the check's tolerance


# ------------------------------------------------------------------------ two-speed touch

def _two_speed(plan, fast=1000.0):
    return plan.model_copy(update={"feeds": plan.feeds.model_copy(
        update={"fast_probe_mm_min": fast})})


def test_two_speed_touch_is_checked_timed_and_only_where_the_dialect_can():
    from programs.cycletime import estimate
    from programs.dialects import get_dialect
    machine, mf, art, plan = golden_setup()
    one = build_program(machine, mf, art, _two_speed(plan))  # two_speed=False: one speed
    two = build_program(machine, mf, art, _two_speed(plan), two_speed=True)
    assert all(mv.locate_feed_mm_min == 0 for mv in one.moves)
    probes = [mv for mv in two.moves if mv.kind == "probe"]
    assert probes and all(mv.locate_feed_mm_min == 1000 and mv.backoff_mm > 0 for mv in probes)
    check_program(two)
    assert estimate(two).estimate_s < estimate(one).estimate_s
    with pytest.raises(ProgramError, match="no two-speed touch"):
        get_dialect("fanuc").render(two)
    bad = replace(probes[0], backoff_mm=two.standoff_mm + 0.5)
    two.moves[two.moves.index(probes[0])] = bad
    with pytest.raises(SafetyError, match="backs off"):
        check_program(two)


@pytest.mark.skipif(shutil.which("rs274") is None, reason="rs274 not installed (LinuxCNC peer)")
def test_linuxcncs_own_interpreter_runs_the_two_speed_touch(tmp_path):
    text = (Path(__file__).parent / "golden" / "linuxcnc-two-speed.ngc").read_text()
    src, out = tmp_path / "p.ngc", tmp_path / "canon.txt"
    src.write_text(text)
    r = subprocess.run([shutil.which("rs274"), "-g", str(src), str(out)], capture_output=True,
                       text=True, timeout=60, cwd=tmp_path, stdin=subprocess.DEVNULL)
    assert r.returncode == 0, r.stdout + r.stderr
    probes = [ln for ln in out.read_text().splitlines() if "STRAIGHT_PROBE(" in ln]
    assert len(probes) == 2 * text.count("(LOG,RUMBA ")  # locate + re-touch per touch


def _latched(plan_fast: float | None, sample_ms: float, feed: float = 300.0) -> np.ndarray:
    """Latched X Y Z of every touch of a linuxcnc program run on the simulator (noise off)."""
    from programs.generate import generate
    machine, mf = load_machine(CONFIG / "machines" / "linuxcnc_xyzbc.yaml")
    art = load_artefact(CONFIG / "artefacts" / "thesis_4ball.yaml")
    plan = load_plan(CONFIG / "plans" / "linuxcnc_4poses.yaml").model_copy(
        update={"poses": [PoseFile(b_deg=0, c_deg=0), PoseFile(b_deg=30, c_deg=120)]})
    plan = plan.model_copy(update={"feeds": plan.feeds.model_copy(
        update={"probe_mm_min": feed, "fast_probe_mm_min": plan_fast})})
    err = load_errors(CONFIG / "errors" / "linuxcnc_xyzbc.yaml")
    err = err.model_copy(update={"probe": err.probe.model_copy(
        update={"sample_period_ms": sample_ms, "touch_noise_um": 0.0})})
    truth = TruthModel.build(machine, mf, art, err)
    g = generate(machine, mf, art, plan, "linuxcnc")
    res = run_sync(truth, g.text, "linuxcnc", seed=5)
    assert res.state == "done" and len(res.rows) == len(g.touches)  # one result per touch
    return np.array([[r.x_mm, r.y_mm, r.z_mm] for r in res.rows])


def test_the_simulator_latches_the_slow_retouch_with_the_slow_speeds_repeatability():
    """A 1 ms sampled latch lies past the contact by feed × 1 ms × U(0, 1): at most 5 µm at
    F300, 16.7 µm at F1000. The two-speed touch locates at F1000 and reports the F300 re-touch:
    every latch within 5 µm of the true contact, as the one-speed F300 touch; a one-speed
    F1000 touch overshoots further (so the bound can tell which one was reported)."""
    exact = _latched(None, 0.0)
    for fast, feed, bound in ((1000.0, 300.0, 5e-3), (None, 300.0, 5e-3)):
        over = np.linalg.norm(_latched(fast, 1.0, feed) - exact, axis=1)
        assert over.max() <= bound + 1e-6 and over.mean() > 0.25 * bound
    fast_only = np.linalg.norm(_latched(None, 1.0, 1000.0) - _latched(None, 0.0, 1000.0),
                               axis=1)
    assert fast_only.max() > 2 * 5e-3


# ------------------------------------------------------------------- candidates and order

def test_candidates_refused_without_building_are_refused_by_building():
    machine, mf = load_machine(CONFIG / "machines" / "linuxcnc_xyzbc.yaml")
    art = load_artefact(CONFIG / "artefacts" / "thesis_4ball.yaml")
    plan = load_plan(CONFIG / "plans" / "linuxcnc_4poses.yaml")
    from contracts.plan_targets import CandidateGrid
    poses = candidate_poses(machine, CandidateGrid(b_step_deg=30, c_step_deg=60))
    d = build_design(machine, art, poses, ("EB0Z",), (1, 1, 1))
    c = Candidates(machine, mf, art, plan, False, poses, d.centres_mm)
    assert c.refuse_table() >= 3
    refused = [i for i, v in c.visits.items() if not v.ok]
    for i in refused[:: max(1, len(refused) // 4)]:  # a spread of them, each really unsafe
        one = plan.model_copy(update={"poses": [PoseFile(b_deg=poses[i][0],
                                                         c_deg=poses[i][1])]})
        with pytest.raises((SafetyError, ProgramError)):
            check_program(build_program(machine, mf, art, one))


def test_c_is_unwrapped_so_no_index_turns_the_long_way():
    assert unwrap_c([0, 330, 30, 180], (-9999, 9999)) == [0, -30, 30, -180]
    assert unwrap_c([10, 350], (-180, 180)) == [10, -10]
    assert unwrap_c([0, 330, 30], (0, 360)) == [0, 330, 30]  # no common shift fits: as given


def test_tour_is_the_fastest_whose_c_order_is_not_monotone():
    c = [0.0, 60.0, 120.0, 180.0, 240.0]
    cost = np.abs(np.subtract.outer(c, c)) / 90.0 + 0.5
    order = order_tour(cost, c)
    assert order[0] == 0 and sorted(order) == list(range(5))
    assert not monotone([c[i] for i in order])
    seq = [*order, 0]
    assert sum(cost[a, b] for a, b in itertools.pairwise(seq)) == pytest.approx(
        2 * 240 / 90 + 5 * 0.5)  # out and back: the least C rotation a closed tour can have


def test_linuxcnc_link_streams_a_two_speed_touch_as_three_blocks_and_one_result():
    from drivers.linuxcnc.program import plan_steps
    text = (Path(__file__).parent / "golden" / "linuxcnc-two-speed.ngc").read_text()
    steps = plan_steps(text)
    first = next(i for i, st in enumerate(steps) if "G38.3" in st.text)
    a, b, c, res = steps[first:first + 4]
    assert a.text.startswith("N") and "G38.3" in a.text
    assert b.text.startswith("G1 X[#5061") and "G38.2" in c.text and res.kind == "result"
    assert a.touch == c.touch == "touch seq 1 pose 0 ball B1 touch 1"  # errors name the touch
    assert sum(st.kind == "result" for st in steps) == text.count("(LOG,RUMBA ")
