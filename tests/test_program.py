"""Program generator: touch geometry (property test over machines, poses and artefacts), path
structure, identities and estimate-based targets."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from contracts.messages import TOUCH_DIRECTIONS
from contracts.setup_files import artefact_from_dict, load_machine, plan_from_dict
from contracts.yaml_files import ConfigError
from identification.kinematics import rotary_columns, tip_minus_ball, to_model
from programs.model import Targets, ball_positions, load_targets
from programs.toolpath import build_program

CONFIG = Path(__file__).resolve().parent.parent / "config"
MACHINES = ["thesis_wcbxfzyt", "seed001_wbzfxyct", "vertical_wcayfxzt"]


def _machine(name: str):
    return load_machine(CONFIG / "machines" / f"{name}.yaml")


def relative(prog, q: np.ndarray, ball_mm: np.ndarray) -> np.ndarray:
    """Tip − ball centre (machine frame) for controller states q (N, 5), straight from the chain."""
    m = prog.machine
    lin = to_model(m, {a: q[:, i] for i, a in enumerate("XYZ")})
    rot = to_model(m, rotary_columns(m, q[:, 3], q[:, 4]))
    return tip_minus_ball(m, {**lin, **rot}, np.broadcast_to(ball_mm, (len(q), 3)), prog.state)


@st.composite
def scenarios(draw):
    name = draw(st.sampled_from(MACHINES))
    machine, mf = _machine(name)
    r1, r2 = machine.rotary_axes
    lo1, hi1 = machine.axes[r1].travel
    lo2, hi2 = machine.axes[r2].travel
    n_poses = draw(st.integers(1, 2))
    poses = [[draw(st.floats(max(lo1, -60), min(hi1, 60))), draw(st.floats(max(lo2, -180),
                                                                           min(hi2, 180)))]
             for _ in range(n_poses)]
    n_balls = draw(st.integers(1, 2))
    balls = []
    for i in range(n_balls):
        rod = draw(st.floats(30, 150))
        balls.append({"id": f"B{i + 1}", "rod_length_mm": rod,
                      "position_mm": [draw(st.floats(-120, 120)), draw(st.floats(-120, 120)),
                                      mf.table.surface_z_mm + rod],
                      "ball_diameter_mm": draw(st.floats(10, 40))})
    art = artefact_from_dict({"name": "random", "balls": balls})
    plan = plan_from_dict({"name": "p", "stylus_diameter_mm": draw(st.floats(1, 8)),
                           "poses": poses, "standoff_mm": draw(st.floats(0.5, 5)),
                           "overtravel_mm": draw(st.floats(0.5, 4))})
    targets = None
    if draw(st.booleans()):  # targets from a last estimate: shifted balls and stylus
        off = st.floats(-0.5, 0.5)
        targets = Targets("estimate", {b["id"]: (draw(off), draw(off), draw(off))
                                       for b in balls},
                          (draw(off) / 10, draw(off) / 10, draw(off) / 10))
    return machine, mf, art, plan, targets


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(scenarios())
def test_every_probing_move_starts_outside_crosses_and_follows_its_direction(case):
    machine, mf, art, plan, targets = case
    prog = build_program(machine, mf, art, plan, targets)
    centres = ball_positions(art, prog.targets)
    probes = [mv for mv in prog.moves if mv.kind == "probe"]
    assert len(probes) == len(prog.touches) == 5 * len(art.balls) * len(plan.poses)
    prev = {mv.block: prog.moves[i - 1] for i, mv in enumerate(prog.moves)}
    for mv in probes:
        t = mv.touch
        ball = art.balls[t.ball_number - 1]
        r_env = ball.diameter_mm / 2 + plan.stylus_radius_mm
        start = np.array(prev[mv.block].target)  # the probe starts where the previous move ended
        q = np.array([start, mv.target])
        r = relative(prog, q, centres[t.ball_number - 1])
        d_start, d_end = np.linalg.norm(r, axis=1)
        assert d_start == pytest.approx(r_env + prog.standoff_mm, abs=1e-9)
        assert d_start > r_env > d_end
        assert d_end == pytest.approx(r_env - prog.overtravel_mm, abs=1e-9)
        u = (r[1] - r[0]) / np.linalg.norm(r[1] - r[0])
        want = (np.array(TOUCH_DIRECTIONS[t.id.touch]) if t.id.touch < 5
                else -np.asarray(machine.spindle_axis))
        assert np.abs(u - want).max() < 1e-9
        assert np.abs(np.array(t.direction) - want).max() < 1e-9
        # through the centre: the start is exactly opposite the direction
        assert np.abs(r[0] / d_start + want).max() < 1e-9


def _thesis(poses, **kw):
    machine, mf = _machine("thesis_wcbxfzyt")
    from contracts.setup_files import load_artefact
    art = load_artefact(CONFIG / "artefacts" / "thesis_4ball.yaml")
    plan = plan_from_dict({"name": "t", "stylus_diameter_mm": 6, "poses": poses, **kw})
    return machine, mf, art, plan


def test_structure_identity_and_retract_before_every_index():
    machine, mf, art, plan = _thesis([[0, 0], [30, 60], [-30, 300]], repeats=2)
    prog = build_program(machine, mf, art, plan)
    seqs = [t.id.seq for t in prog.touches]
    assert seqs == list(range(1, 5 * 4 * 3 * 2 + 1))
    ids = {(t.id.repeat, t.id.pose, t.id.ball, t.id.touch) for t in prog.touches}
    assert len(ids) == len(seqs)  # every touch has its own identity
    # per ball: touches 1-4 in some order, then the pole last
    for i in range(0, len(prog.touches), 5):
        group = prog.touches[i:i + 5]
        assert len({t.id.ball for t in group}) == 1
        assert sorted(t.id.touch for t in group[:4]) == [1, 2, 3, 4] and group[4].id.touch == 5
    # before every rotary move: a retract-only block to at least the pose's highest ball top
    for i, mv in enumerate(prog.moves):
        if set(mv.words) & {"B", "C"}:
            assert set(mv.words) <= {"B", "C"}
            before = prog.moves[i - 1]
            assert before.words == ("Z",)
            assert before.target[2] > max(t.centre[2] for t in prog.touches) + 12.7


def test_ball_order_shortens_the_tour():
    machine, mf, art, plan = _thesis([[0, 0]])
    prog = build_program(machine, mf, art, plan)
    order = [t.id.ball for t in prog.touches[::5]]
    centres = {t.id.ball: np.array(t.centre[:2]) for t in prog.touches}

    def length(o):
        return sum(np.linalg.norm(centres[a] - centres[b]) for a, b in itertools.pairwise(o))

    best = min(length(list(p)) for p in itertools.permutations(order))
    assert length(order) == pytest.approx(best)


def test_estimate_targets_shift_touches_and_shrink_standoff(tmp_path):
    machine, mf, art, plan = _thesis([[0, 0]])
    est = {"setup": {"balls": {b: {"value": [100.0, -50.0, 20.0]} for b in art.ids},
                     "probe": {"value": [0.0, 0.0, 10.0]}}}
    p = tmp_path / "estimate.json"
    p.write_text(json.dumps(est))
    targets = load_targets(p, art)
    nominal = build_program(machine, mf, art, plan)
    shifted = build_program(machine, mf, art, plan, targets)
    assert shifted.standoff_mm == 1.0 < nominal.standoff_mm
    d = np.array(shifted.touches[0].centre) - np.array(nominal.touches[0].centre)
    # controller axes are the tool's motion relative to the workpiece (signs in the machine
    # file): the ball offset adds; a tip 0.01 mm further out along the spindle (+z) subtracts
    assert d == pytest.approx([0.1, -0.05, 0.02 - 0.01], abs=1e-9)


@pytest.mark.parametrize("payload, key", [
    ({}, "setup.balls"),
    ({"setup": {"balls": {}}}, "no estimate for balls"),
    ({"setup": {"balls": {b: {"value": [1, 2]} for b in ("B1", "B2", "B3", "B4")}}},
     "setup.balls.B1.value"),
])
def test_bad_estimate_file_names_the_key(tmp_path, payload, key):
    _, _, art, _ = _thesis([[0, 0]])
    p = tmp_path / "e.json"
    p.write_text(json.dumps(payload))
    with pytest.raises(ConfigError, match=key):
        load_targets(p, art)


def test_nominal_targets_default():
    machine, mf, art, plan = _thesis([[0, 0]])
    assert build_program(machine, mf, art, plan).targets == Targets()


def test_generate_checks_renders_and_times(tmp_path):
    from programs.generate import generate

    machine, mf, art, plan = _thesis([[0, 0], [30, 60]])
    g = generate(machine, mf, art, plan, "heidenhain")
    assert g.text.startswith("0 BEGIN PGM RUMBA MM") and len(g.touches) == 40
    assert set(g.aux_files) == {f"RUMBA_{b}.A" for b in art.ids}
    assert 0 < g.lower_bound_s < g.estimated_s < 3 * g.lower_bound_s
    # one estimate: the header prints the one the result carries
    assert f"CYCLE TIME {g.cycle_time.summary().replace('(', '').replace(')', '')}" in g.text
    table = g.touch_table()
    assert table.ids() == tuple(t.id for t in g.touches)
    assert table.get(3).feed_mm_min == plan.feeds.probe_mm_min


def test_cli_with_targets_from_an_estimate(tmp_path, capsys):
    from daemon.cli.main import main

    est = {"setup": {"balls": {b: {"value": [10.0, 0.0, 0.0]} for b in ("B1", "B2", "B3", "B4")},
                     "probe": {"value": [0.0, 0.0, 0.0]}}}
    (tmp_path / "e.json").write_text(json.dumps(est))
    rc = main(["gcode", "--machine", str(CONFIG / "machines" / "thesis_wcbxfzyt.yaml"),
               "--artefact", str(CONFIG / "artefacts" / "thesis_4ball.yaml"), "--plan",
               str(CONFIG / "plans" / "thesis_ch3_7poses.yaml"), "--dialect", "siemens",
               "--targets", str(tmp_path / "e.json"), "-o", str(tmp_path / "p.mpf")])
    out = capsys.readouterr().out
    assert rc == 0 and "targets estimate" in out and "140 touches" in out
    assert "; STANDOFF 1 OVERTRAVEL 1" in (tmp_path / "p.mpf").read_text()
