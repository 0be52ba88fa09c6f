"""Pre-release safety check: shipped plans pass; leaving the travel, entering a keep-out, too high
a feed or a bad index are refused with a one-line message naming block, pose, ball and reason."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import yaml

from contracts.setup_files import (
    artefact_from_dict,
    load_artefact,
    load_machine,
    load_plan,
    machine_from_dict,
    plan_from_dict,
)
from daemon.cli.main import main
from programs.safety import SafetyError, check_program
from programs.toolpath import build_program

ROOT = Path(__file__).resolve().parent.parent
CONFIG = ROOT / "config"
SHIPPED = [
    ("thesis_wcbxfzyt", "thesis_4ball", "thesis_ch3_7poses"),
    ("thesis_wcbxfzyt", "thesis_4ball", "thesis_annexB_14poses"),
    ("thesis_wcbxfzyt", "thesis_4ball_scaled", "thesis_annexB_14poses"),
    ("seed001_wbzfxyct", "seed001_5ball", "seed001_11poses"),
    ("vertical_wcayfxzt", "vertical_4ball", "vertical_18poses"),
]


def _load(m: str, a: str, p: str):
    machine, mf = load_machine(CONFIG / "machines" / f"{m}.yaml")
    return (machine, mf, load_artefact(CONFIG / "artefacts" / f"{a}.yaml"),
            load_plan(CONFIG / "plans" / f"{p}.yaml"))


@pytest.mark.parametrize("m, a, p", SHIPPED)
def test_shipped_plans_pass(m, a, p):
    """(thesis_ch4_175poses passes too: benchmarks/bench_cycletime.py checks it, ~3 s.)"""
    report = check_program(build_program(*_load(m, a, p)))
    assert report.min_slack_mm >= 0


def _thesis_machine(**changes):
    data = yaml.safe_load((CONFIG / "machines" / "thesis_wcbxfzyt.yaml").read_text())
    for path, value in changes.items():
        node = data
        keys = path.split(".")
        for k in keys[:-1]:
            node = node.setdefault(k, {})
        node[keys[-1]] = value
    return machine_from_dict(data)


def _small_plan(**kw):
    return plan_from_dict({"name": "small", "stylus_diameter_mm": 6,
                           "poses": kw.pop("poses", [[0, 0], [30, 60]]), **kw})


ART = load_artefact(CONFIG / "artefacts" / "thesis_4ball.yaml")


def test_travel_limit_is_refused_naming_block_pose_and_axis():
    machine, mf = _thesis_machine(**{"axes.X.travel_mm": [-350, 100]})
    with pytest.raises(SafetyError) as e:
        check_program(build_program(machine, mf, ART, _small_plan()))
    msg = str(e.value)
    assert "\n" not in msg
    assert msg.startswith("block N") and "pose 0 (B0 C0)" in msg
    assert "outside the X travel [-350, 100] mm" in msg and "ball B" in msg


def test_rotary_travel_is_refused():
    machine, mf = _thesis_machine(**{"axes.B.travel_deg": [-20, 20]})
    with pytest.raises(SafetyError, match=r"pose 1 \(B30 C60\).*B30.0000 is outside the B travel"):
        check_program(build_program(machine, mf, ART, _small_plan()))


def test_keep_out_box_in_the_path_is_refused():
    machine, mf = _thesis_machine(keep_out=[{"name": "clamp-1", "min_mm": [-140, -120, 140],
                                             "max_mm": [-125, -60, 160]}])
    with pytest.raises(SafetyError, match=r"ball B1.*keep-out box clamp-1"):
        check_program(build_program(machine, mf, ART, _small_plan(poses=[[0, 0]])))


def test_neighbour_ball_in_the_path_is_refused():
    # B2 put 20 mm beside B1 at the same height: B1's touches collide with it
    balls = [{"id": "B1", "position_mm": [-100, -80, 152], "rod_length_mm": 152},
             {"id": "B2", "position_mm": [-100, -55, 152], "rod_length_mm": 152}]
    art = artefact_from_dict({"name": "tight", "balls": balls})
    machine, mf = _thesis_machine()
    with pytest.raises(SafetyError, match=r"from (ball|the rod of ball) B[12]"):
        check_program(build_program(machine, mf, art, _small_plan(poses=[[0, 0]])))


def test_table_keep_out_is_refused():
    # a ball too close to the table: its equator touches would graze the pallet
    balls = [{"id": "B1", "position_mm": [0, 0, 7], "rod_length_mm": 7}]
    art = artefact_from_dict({"name": "low", "balls": balls})
    machine, mf = _thesis_machine()
    with pytest.raises(SafetyError, match="table keep-out"):
        check_program(build_program(machine, mf, art, _small_plan(poses=[[0, 0]])))


def test_feed_bounds_from_the_machine():
    machine, mf = _thesis_machine(**{"dynamics.max_probe_feed_mm_min": 200})
    with pytest.raises(SafetyError, match="probing feed 300 mm/min exceeds"):
        check_program(build_program(machine, mf, ART, _small_plan()))
    machine, mf = _thesis_machine(**{"dynamics.max_feed_mm_min": 1000})
    with pytest.raises(SafetyError, match="feed 2000 mm/min exceeds"):
        check_program(build_program(machine, mf, ART, _small_plan()))


def test_index_without_retract_is_refused():
    machine, mf = _thesis_machine()
    prog = build_program(machine, mf, ART, _small_plan())
    i = next(i for i, mv in enumerate(prog.moves) if mv.block > 3 and set(mv.words) == {"B", "C"})
    prev = prog.moves[i - 2]  # skip the retract: index right where the last touch ended
    moves = list(prog.moves)
    low = dataclasses.replace(moves[i], target=(*prev.target[:3], *moves[i].target[3:]))
    moves[i - 1] = dataclasses.replace(moves[i - 1], target=prev.target, words=("Z",))
    moves[i] = low
    prog.moves = moves
    with pytest.raises(SafetyError, match=r"rotary index passes .* below the top of"):
        check_program(prog)


def test_probe_off_its_line_is_refused():
    machine, mf = _thesis_machine()
    prog = build_program(machine, mf, ART, _small_plan(poses=[[0, 0]]))
    i = next(i for i, mv in enumerate(prog.moves) if mv.kind == "probe")
    mv = prog.moves[i]
    t = list(mv.target)
    t[2] -= 1.0  # dip 1 mm: no longer along the touch direction
    prog.moves[i] = dataclasses.replace(mv, target=tuple(t))
    with pytest.raises(SafetyError, match="not the probing direction"):
        check_program(prog)


def test_cli_refuses_unsafe_plan_with_one_line_exit_2(tmp_path, capsys):
    data = yaml.safe_load((CONFIG / "machines" / "thesis_wcbxfzyt.yaml").read_text())
    data["axes"]["Z"]["travel_mm"] = [-250, 150]
    m = tmp_path / "m.yaml"
    m.write_text(yaml.safe_dump(data))
    rc = main(["gcode", "--machine", str(m), "--artefact",
               str(CONFIG / "artefacts" / "thesis_4ball.yaml"), "--plan",
               str(CONFIG / "plans" / "thesis_ch3_7poses.yaml"), "--dialect", "linuxcnc",
               "-o", str(tmp_path / "p.ngc")])
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert err.count("\n") == 0
    assert err.startswith("error: unsafe program refused: block N")
    assert "outside the Z travel [-250, 150] mm" in err
    assert not (tmp_path / "p.ngc").exists()


def test_cli_prints_touch_count_and_times(tmp_path, capsys):
    rc = main(["gcode", "--machine", str(CONFIG / "machines" / "thesis_wcbxfzyt.yaml"),
               "--artefact", str(CONFIG / "artefacts" / "thesis_4ball.yaml"), "--plan",
               str(CONFIG / "plans" / "thesis_ch3_7poses.yaml"), "--dialect", "heidenhain",
               "-o", str(tmp_path / "p.h")])
    out = capsys.readouterr().out
    assert rc == 0
    assert "140 touches" in out and "estimated" in out and "lower bound" in out
    assert (tmp_path / "RUMBA_B1.A").exists()
    assert (tmp_path / "p.h").read_text().startswith("0 BEGIN PGM RUMBA MM\n")


def test_stylus_stem_is_a_keep_out_body_too():
    """A tip segment passing 48 mm under ball B1 (tip clear of ball and rod) while the 50 mm
    stem above it sweeps through the ball: refused only because of the stem."""
    from programs.clearance import keepout_slack
    from tests.regen_golden import golden_program

    prog = golden_program()
    pa = np.array([[-150.0, -70.0, 104.0]])
    pb = np.array([[-50.0, -70.0, 104.0]])
    own = np.array([-1])
    tip_only, _ = keepout_slack(prog, pa, pb, own)
    assert tip_only[0] > 0
    slack, explain = keepout_slack(prog, pa, pb, own, np.array([[0.0, 0.0, 1.0]]))
    assert slack[0] < 0 and explain(0).startswith("stylus stem comes") and "ball B1" in explain(0)
    short = prog.plan.model_copy(update={"stylus_length_mm": 30.0})
    prog.plan = short
    assert keepout_slack(prog, pa, pb, own, np.array([[0.0, 0.0, 1.0]]))[0][0] > 0


def test_parallelogram_distances_match_brute_force():
    from programs.clearance import point_par, seg_par

    rng = np.random.default_rng(7)
    n = 100
    p0, e1, e2 = rng.normal(size=(n, 3)) * 10, rng.normal(size=(n, 3)) * 10, \
        rng.normal(size=(n, 3)) * 10
    c, r0, r1 = rng.normal(size=(n, 3)) * 15, rng.normal(size=(n, 3)) * 15, \
        rng.normal(size=(n, 3)) * 15
    g = np.linspace(0, 1, 101)
    s, t = (x.ravel()[None, :, None] for x in np.meshgrid(g, g))
    face = p0[:, None] + s * e1[:, None] + t * e2[:, None]
    brute = np.linalg.norm(face - c[:, None], axis=2).min(axis=1)
    exact = point_par(c, p0, e1, e2)
    assert np.all(exact <= brute + 1e-9)
    assert np.all(brute - exact < 0.5)  # the brute-force grid is 1 % of the edge lengths
    seg = r0[:, None] + np.linspace(0, 1, 51)[None, :, None] * (r1 - r0)[:, None]
    brute_seg = np.array([np.min(np.linalg.norm(face[i][:, None] - seg[i][None], axis=2))
                          for i in range(0, n, 10)])
    exact_seg = seg_par(r0, r1, p0, e1, e2)[::10]
    assert np.all(exact_seg <= brute_seg + 1e-9)
    assert np.all(brute_seg - exact_seg < 1.0)
    assert np.any(seg_par(r0, r1, p0, e1, e2) == 0.0)  # some segments pierce their face
