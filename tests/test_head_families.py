"""Swivel head B + table C, fork head A/C on a bridge, nutating 45° table — inclined
axes in the chain, the identifiable link set by rank, tilted-probe programs (tool-frame touches,
TCPM off), the safety check refusing head and rod collisions, and the simulated run identifying
the injected links (the 20-seed acceptance: benchmarks/bench_head_families.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml

from benchmarks.rigs.daemon_helpers import CONFIG
from contracts.setup_files import load_artefact, load_machine, load_plan, machine_from_dict
from contracts.yaml_files import ConfigError
from daemon.analysis.touch_centres import rows_to_centres
from identification.estimate import estimate
from identification.identifiability import identifiable_links, nominal_centres
from identification.kinematics import ChainState, axis_frame, frames, to_model
from programs.dialects import DIALECTS, get_dialect
from programs.geometry import ProgramError
from programs.model import Move
from programs.safety import SafetyError, check_program
from programs.toolpath import build_program
from simulators.errors_schema import load_errors
from simulators.offline import run_sync
from simulators.truth import TruthModel

ARTEFACT = CONFIG / "artefacts/vertical_4ball.yaml"
# The simulated probing noise of the one-run tests below: deterministic, as in
# tests/test_e2e_transports.py. 3u on 8 links fails by chance in a few % of draws (the fork
# head's seed 3 puts EB0C at 3.5u: its C tilt and the Z squareness are 0.9 correlated at A ±30°);
# the coverage over 20 seeds is benchmarks/bench_head_families.py's (README).
NOISE_SEED = 4
FAMILIES = {"swivelhead": "swivelhead_wcfxyzbt", "forkhead": "forkhead_wxfyzcat",
            "nutating": "nutating_wcbyfxzt"}
PLANS = {"swivelhead": "swivelhead_12poses", "forkhead": "forkhead_11poses",
         "nutating": "nutating_12poses"}
# The rank computation (identification.identifiability: a link is kept when it raises the
# numerical rank of the centre Jacobian beyond the setup columns) on each shipped plan.
RANK_SETS = {
    "swivelhead": ("EX0C", "EA0C", "EB0C", "EA0B", "EC0B", "EC0Y", "EA0Z", "EB0Z"),
    "forkhead": ("EA0C", "EB0C", "EY0A", "EB0A", "EC0A", "EC0Y", "EA0Z", "EB0Z"),
    "nutating": ("EA0B", "EC0B", "EX0C", "EA0C", "EB0C", "EC0X", "EA0Z", "EB0Z"),
}


def _family(name: str):
    machine, mf = load_machine(CONFIG / f"machines/{FAMILIES[name]}.yaml")
    return machine, mf, load_artefact(ARTEFACT), load_plan(CONFIG / f"plans/{PLANS[name]}.yaml")


def _rot(machine, **rot: float) -> np.ndarray:
    """Rotation of the last workpiece frame (foundation ← workpiece) at a rotary pose."""
    zero = np.zeros(1)
    q = {"X": zero, "Y": zero, "Z": zero, **{k: np.array([v]) for k, v in rot.items()}}
    f_w, _ = frames(machine, to_model(machine, q), ChainState())
    return f_w[0, :3, :3]


# ------------------------------------------------------------------------- machine files


def test_nutating_b_turns_about_its_inclined_direction():
    machine, *_ = _family("nutating")
    b = machine.axes["B"]
    d = np.array(b.direction)
    assert d == pytest.approx([0, math.sqrt(0.5), math.sqrt(0.5)])
    r = _rot(machine, B=180.0, C=0.0)
    # half a turn about (0, 1, 1)/√2 lays the table top (z) onto +y: the face turns vertical
    assert r @ [0, 0, 1] == pytest.approx([0, 1, 0], abs=1e-12)
    assert r @ d == pytest.approx(d, abs=1e-12)  # the axis is its own fixed direction
    # principal axes keep no frame: today's machines are computed exactly as before
    assert axis_frame(machine.axes["C"]) is None and b.inclined and not machine.axes["C"].inclined


def test_location_errors_of_an_inclined_axis_live_in_its_own_frame():
    """EX0B of the 45° B shifts the B line along R0·x (= x here), EZ0B along R0·z (tilted):
    the shifted line's points are fixed by the B motion; EA0B tilts it about R0·x."""
    machine, *_ = _family("nutating")
    b = machine.axes["B"]
    r0 = axis_frame(b)
    p = np.array(b.point_mm)
    from identification.kinematics import axis_htm

    def motion(links: dict, deg: float) -> np.ndarray:
        """The body's motion from B0 to B``deg`` in the parent frame: T(q) · T(0)⁻¹."""
        t = axis_htm(b, np.radians([deg, 0.0]), links)
        return t[0] @ np.linalg.inv(t[1])

    for name, shift in (("EX0B", r0 @ [1, 0, 0]), ("EZ0B", r0 @ [0, 0, 1])):
        m = motion({name: 0.5}, 70.0)
        point = p + 0.5 * shift + 30.0 * np.array(b.direction)  # on the shifted line
        assert m[:3, :3] @ point + m[:3, 3] == pytest.approx(point, abs=1e-9), name
        nominal = p + 30.0 * np.array(b.direction)  # the nominal line is not fixed any more
        assert np.linalg.norm(m[:3, :3] @ nominal + m[:3, 3] - nominal) > 0.1, name
    m = motion({"EA0B": 1e-3}, 90.0)
    tilted = r0 @ np.array([0.0, math.cos(1e-3), math.sin(1e-3)])  # y turned about x, in R0
    assert m[:3, :3] @ tilted == pytest.approx(tilted, abs=1e-12)
    assert np.linalg.norm(m[:3, :3] @ np.array(b.direction) - b.direction) > 1e-4


def test_an_axis_direction_far_from_its_letter_is_a_config_error():
    doc = yaml.safe_load((CONFIG / "machines/nutating_wcbyfxzt.yaml").read_text())
    doc["axes"]["B"]["direction"] = [0, 0.3, 0.95]  # 72° from y: not a B any more
    with pytest.raises(ConfigError, match=r"axis B: direction .* more than 60° from y"):
        machine_from_dict(doc, "nutating.yaml")
    doc["axes"]["B"]["direction"] = [0, 1, 1]  # not unit: normalised on load
    m, _ = machine_from_dict(doc, "nutating.yaml")
    assert m.axes["B"].direction == pytest.approx((0, math.sqrt(0.5), math.sqrt(0.5)))


@pytest.mark.parametrize("family", list(FAMILIES))
def test_identifiable_set_is_the_rank_computation(family):
    machine, _, artefact, plan = _family(family)
    poses = [(p.b_deg, p.c_deg) for p in plan.poses]
    ida = identifiable_links(machine, artefact, nominal_centres(machine, artefact, poses))
    assert ida.links == RANK_SETS[family]
    assert len(machine.location_error_names()) == 14 and len(ida.dropped) == 6


# ------------------------------------------------------------------------------ programs


@pytest.mark.parametrize("family", list(FAMILIES))
def test_shipped_plan_builds_safe_and_touches_in_the_tool_frame(family):
    machine, mf, artefact, plan = _family(family)
    prog = build_program(machine, mf, artefact, plan)
    check_program(prog)
    assert prog.tilted == (family != "nutating")
    assert len(prog.touches) == 5 * len(artefact.balls) * len(plan.poses)
    r1, r2 = machine.rotary_axes
    from programs.geometry import pose_frame

    for t in prog.touches[:: 7]:
        pf = pose_frame(machine, {r1: t.b_deg, r2: t.c_deg}, prog.state)
        d = np.array(t.direction)
        if t.id.touch == 5:
            assert d == pytest.approx(-pf.spindle, abs=1e-12)  # the pole against the spindle
        else:
            assert abs(d @ pf.spindle) < 1e-12  # an equator touch ⊥ the spindle at that pose
        # the probing line runs along the touch direction through the ball centre
        u = np.array(t.end) - np.array(t.start)
        assert pf.jac @ u / np.linalg.norm(pf.jac @ u) == pytest.approx(d, abs=1e-9)
    if prog.tilted:  # at a tilted pose the equator leaves the machine X-Y plane
        tilted = [t for t in prog.touches if t.b_deg != 0 and t.id.touch < 5]
        assert tilted and any(abs(t.direction[2]) > 0.1 for t in tilted)
        for pose in {t.id.pose for t in tilted}:
            assert max(abs(t.direction[2]) for t in tilted if t.id.pose == pose) > 0.1


@pytest.mark.parametrize("family", ["swivelhead", "forkhead"])
@pytest.mark.parametrize("dialect", sorted(DIALECTS))
def test_every_dialect_states_and_sets_tcpm_off(family, dialect):
    machine, mf, artefact, plan = _family(family)
    plan = plan.model_copy(update={"poses": plan.poses[:1]})
    prog = build_program(machine, mf, artefact, plan)
    d = get_dialect(dialect)
    text = d.render(prog)
    assert f"TILTED PROBE: {d.tcpm_note}" in text and d.tcpm_note
    lines = [ln.split(" ", 1)[-1] if dialect == "heidenhain" else ln for ln in text.splitlines()]
    first_move = next(i for i, ln in enumerate(lines) if ln.startswith(("N1 ", "L ")))
    assert d.tcpm_off in lines[:first_move]  # before any motion


def test_a_table_table_program_has_no_tcpm_block():
    machine, mf, artefact, plan = _family("nutating")
    text = get_dialect("fanuc").render(build_program(machine, mf, artefact, plan))
    assert "TILTED PROBE" not in text and "\nG49\n" not in text


def test_a_pose_whose_head_hits_a_ball_cannot_become_a_program():
    machine, mf, artefact, plan = _family("swivelhead")
    bad = plan.model_copy(update={"poses": [plan.poses[0].model_copy(update={"b_deg": -60.0})]})
    with pytest.raises(ProgramError, match=r"pose 0 \(B-60 C0\), ball B\d: no clear tilted-probe "
                                           r"path \((head-housing|spindle-nose) comes"):
        build_program(machine, mf, artefact, bad)


def test_safety_refuses_a_program_planned_for_a_slimmer_head():
    """The program built for the shipped head (housing Ø230 mm) is checked on a machine whose
    housing is Ø400 mm: the safety check refuses it, naming the block and the body."""
    machine, mf, artefact, plan = _family("swivelhead")
    plan = plan.model_copy(update={"poses": plan.poses[:1]})  # B-40 C0
    prog = build_program(machine, mf, artefact, plan)
    check_program(prog)
    wide = [b.model_copy(update={"radius_mm": 200.0}) if b.name == "head-housing" else b
            for b in mf.tool.bodies]
    prog.machine_file = mf.model_copy(update={"tool": mf.tool.model_copy(
        update={"bodies": wide})})
    with pytest.raises(SafetyError, match=r"block N\d+ .*: head-housing comes "
                                          r"-?\d+\.\d+ mm from (the rod of ball|ball|the table)"):
        check_program(prog)


def test_safety_refuses_a_move_through_a_rod():
    """A deliberately bad block: across from a corner to a point on ball B2's rod (30 mm below
    its centre along the rod) at a tilted pose."""
    machine, mf, artefact, plan = _family("forkhead")
    plan = plan.model_copy(update={"poses": [p for p in plan.poses if p.b_deg != 0][:1]})
    prog = build_program(machine, mf, artefact, plan)
    check_program(prog)
    k = next(i for i, mv in enumerate(prog.moves) if mv.ball == "B2" and mv.kind == "feed")
    from programs.geometry import pose_frame

    mv = prog.moves[k]
    r1, r2 = prog.rotary
    pf = pose_frame(machine, {r1: mv.target[3], r2: mv.target[4]}, prog.state)
    rod_w = prog.ball_positions_mm()[1] - np.array([0.0, 0.0, 30.0])
    q = pf.solve(machine, rod_w[None, :], prog.state)[0]
    prog.moves.insert(k + 1, Move(mv.block, "feed", (*map(float, q), *mv.target[3:]),
                                  ("X", "Y", "Z"), feed_mm_min=1000.0, pose=mv.pose, ball="B2"))
    with pytest.raises(SafetyError, match=r"rod of ball B2"):
        check_program(prog)


# ----------------------------------------------------------------------------- simulator


@pytest.mark.parametrize(("family", "dialect"), [("swivelhead", "siemens"),
                                                  ("forkhead", "heidenhain"),
                                                  ("nutating", "linuxcnc")])
def test_simulated_run_identifies_the_injected_links(family, dialect):
    """Render, run on the virtual controller (same contact and latch physics), fit the
    centres and identify: the rank set, each link within 3u of the errors file's truth."""
    machine, mf, artefact, plan = _family(family)
    errors_path = CONFIG / f"errors/{FAMILIES[family]}.yaml"
    truth = TruthModel.build(machine, mf, artefact, load_errors(errors_path))
    d = get_dialect(dialect)
    prog = build_program(machine, mf, artefact, plan, two_speed=d.two_speed)
    res = run_sync(truth, d.render(prog), dialect, files=d.aux_files(prog), seed=NOISE_SEED)
    assert res.state == "done", res.alarm
    assert len(res.rows) == len(prog.touches)
    data = rows_to_centres(res.rows, artefact, truth.stylus_radius_mm)
    with np.errstate(all="ignore"):
        est = estimate(machine, artefact, data.centres, None)
    si = est.links_si()
    assert tuple(si) == RANK_SETS[family]
    want = yaml.safe_load(errors_path.read_text())["links"]
    for name, (value, std, _) in si.items():
        assert abs(value - want[name]) <= 3 * std, (name, value, want[name], std)


def test_the_latch_numbers_tilted_touches_as_the_program_does():
    """The simulator recognises a tilted touch in the tool frame: every touch of a visit keeps
    its number (before: 0 for all, each drawing its own 'per-visit' centre scatter)."""
    machine, mf, artefact, plan = _family("forkhead")
    plan = plan.model_copy(update={"poses": plan.poses[:1]})  # A-30 C90
    truth = TruthModel.build(machine, mf, artefact, load_errors(
        CONFIG / f"errors/{FAMILIES['forkhead']}.yaml"))
    prog = build_program(machine, mf, artefact, plan)
    assert prog.tilted
    res = run_sync(truth, get_dialect("fanuc").render(prog), "fanuc", seed=NOISE_SEED)
    want = {t.id.seq: t.id.touch for t in prog.touches}
    got = {t.seq: t.touch for t in res.controller.touches if t.triggered}
    assert got == want
