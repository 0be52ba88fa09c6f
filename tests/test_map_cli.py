"""`rumba map`: placements in, the map's JSON (contracts/linear_map.py) and predictions out;
a saved map predicts the same; every bad input is one error line and exit 2 (a fuzzed points
file included: tracebacks 0)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from contracts.linear_map import SCHEMA, load_map
from contracts.probing_log import write_log
from contracts.setup_files import load_artefact, load_machine
from simulators.exact_log import THESIS_LINKS_UM_URAD, to_internal
from tests.map_helpers import map_truth, moved, placement, with_true_distance, write_artefact

ROOT = Path(__file__).resolve().parent.parent


def run_cli(argv: list[str]) -> tuple[int, str, str]:
    """The CLI in-process (module fixtures cannot use capsys)."""
    import io
    from contextlib import redirect_stderr, redirect_stdout

    from daemon.cli.main import main

    out, err = io.StringIO(), io.StringIO()
    with redirect_stdout(out), redirect_stderr(err):
        code = main(argv)
    return code, out.getvalue(), err.getvalue()
MACHINE = ROOT / "config" / "machines" / "thesis_wcbxfzyt.yaml"
POSES = [(b, c) for b in (-40.0, 0.0, 40.0) for c in range(0, 360, 60)]


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """Two placements and a held-out one of a mapped thesis machine (0.3 µm touch noise), as
    probing logs and artefact files; the map of the first two, written by the CLI."""
    tmp = tmp_path_factory.mktemp("map")
    m, _ = load_machine(MACHINE)
    art = load_artefact(ROOT / "config" / "artefacts" / "thesis_4ball.yaml")
    truth = map_truth(m, seed=4, order=2, links=to_internal(THESIS_LINKS_UM_URAD),
                      ranges_mm={"X": [-400, 400], "Y": [-300, 300], "Z": [-100, 400]})
    rng = np.random.default_rng(2)
    out = {}
    for k, (a, poses) in enumerate([(art, POSES), (moved(art, (30.0, -20.0, 100.0), 1.3), POSES),
                                    (moved(art, (-20.0, 10.0, 50.0), 1.1), POSES[1::2])]):
        balls = rng.normal(0, 0.2, (4, 3))
        a = with_true_distance(a, balls) if k == 0 else a
        _, rows, _ = placement(truth, f"run{k}", a, poses, balls, touch_noise_um=0.3, seed=k)
        write_log(tmp / f"log{k}.csv", rows)
        write_artefact(a, tmp / f"art{k}.yaml")
        out[k] = (str(tmp / f"log{k}.csv"), str(tmp / f"art{k}.yaml"))
    (tmp / "points.csv").write_text("# three points\nx_mm,y_mm,z_mm\n0,0,100\n20,-30,120\n"
                                    "-50,40,90\n")
    code, so, se = run_cli(["map", "--machine", str(MACHINE), "--placement", *out[0],
                            "--placement", *out[1], "--holdout", *out[2], "--max-degree", "2",
                            "--json", str(tmp / "map.json"), "--predict",
                            str(tmp / "points.csv"), "--out", str(tmp / "pred.csv"),
                            "--limit-um", "10,30"])
    assert code == 0, se
    return tmp, out, so


def test_the_map_json_holds_functions_observability_figures_and_holdout(files):
    tmp, _, stdout = files
    doc = load_map(tmp / "map.json")
    raw = json.loads((tmp / "map.json").read_text())
    assert raw["schema"] == SCHEMA
    assert len(doc.functions) == 18 and {f.name for f in doc.functions} == {
        f"E{c}{a}" for c in "XYZABC" for a in "XYZ"}
    assert [a.axis for a in doc.basis.axes] == ["X", "Y", "Z"]
    assert all(1 <= a.degree <= 2 for a in doc.basis.axes)
    f = next(f for f in doc.functions if f.name == "EYX")
    assert len(f.x_mm) == len(f.value) == len(f.u) == 21 and "EYX_P1" in f.absorbed
    assert doc.observability.scale_observable  # the first artefact's calibrated distance
    assert "valid for this stylus" in doc.observability.unobservable["EAY"]
    assert len(doc.parameters.names) == len(doc.parameters.values) == len(
        doc.parameters.covariance)
    fig = doc.figures.volumetric_max_um
    assert fig.value_um > 1.0 and fig.u_um and fig.status in ("PASS", "WARN", "FAIL")
    assert doc.holdout is not None and doc.holdout.rms_after_um < doc.holdout.rms_before_um
    assert "Volumetric error over the covered box" in stdout


def test_predictions_and_a_saved_map_agree(files):
    tmp, _, _ = files
    lines = (tmp / "pred.csv").read_text().splitlines()
    assert lines[0] == "x_mm,y_mm,z_mm,ex_um,ey_um,ez_um,ux_um,uy_um,uz_um" and len(lines) == 4
    code, _, se = run_cli(["map", "--machine", str(MACHINE), "--map", str(tmp / "map.json"),
                           "--predict", str(tmp / "points.csv"), "--out", str(tmp / "p2.csv")])
    assert code == 0, se
    a = np.loadtxt(tmp / "pred.csv", delimiter=",", skiprows=1)
    b = np.loadtxt(tmp / "p2.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(a, b, atol=2e-4)  # 4 decimals of µm written
    assert np.all(a[:, 6:] > 0)


def test_a_point_outside_the_covered_box_is_refused_by_line(files, tmp_path):
    tmp, _, _ = files
    box = load_map(tmp / "map.json").basis.axes[1].range_mm
    pts = tmp_path / "pts.csv"
    pts.write_text(f"x_mm,y_mm,z_mm\n0,0,100\n0,{box[1] + 1:.3f},100\n")
    code, _, se = run_cli(["map", "--machine", str(MACHINE), "--map", str(tmp / "map.json"),
                           "--predict", str(pts), "--out", str(tmp_path / "o.csv")])
    assert code == 2 and se.count("\n") == 1
    assert f"{pts}: line 3: column y_mm" in se and "outside the covered range" in se
    assert not (tmp_path / "o.csv").exists()


@pytest.mark.parametrize("args, says", [
    ([], "--placement LOG ARTEFACT"),
    (["--placement", "L", "A", "--map", "M"], "one of the two"),
    (["--map", "M", "--predict", "P"], "--predict POINTS.csv and --out PRED.csv go together"),
    (["--placement", "L", "A"], "nothing to write"),
    (["--placement", "L", "A", "--json", "o", "--degrees", "2,x,1"], "--degrees"),
    (["--placement", "L", "A", "--json", "o", "--limit-um", "5,2"], "--limit-um"),
    (["--placement", "L", "A", "--json", "o", "--max-degree", "12"], "--max-degree"),
    (["--placement", "missing.csv", "{art0}", "--json", "o"], "missing.csv"),
    (["--placement", "{log0}", "{art1bad}", "--json", "o"], "unknown ball"),
    (["--map", "{badjson}", "--predict", "{points}", "--out", "o"], "not a JSON map file"),
    (["--map", "{log0}", "--predict", "{points}", "--out", "o"], "not a JSON map file"),
])
def test_bad_input_is_one_line_and_exit_2(files, tmp_path, args, says):
    tmp, out, _ = files
    (tmp_path / "bad.json").write_text("{not json")
    art = load_artefact(out[1][1])
    from dataclasses import replace

    from identification.model import Ball
    other = replace(art, balls=tuple(Ball(f"Q{i}", b.position_mm) for i, b in
                                     enumerate(art.balls)), distances=())
    write_artefact(other, tmp_path / "other.yaml")
    subs = {"{art0}": out[0][1], "{log0}": out[0][0], "{art1bad}": str(tmp_path / "other.yaml"),
            "{badjson}": str(tmp_path / "bad.json"), "{points}": str(tmp / "points.csv")}
    argv = ["map", "--machine", str(MACHINE), *[subs.get(a, a) for a in args]]
    code, _, se = run_cli(argv)
    assert code == 2, (code, se)
    assert se.startswith("error: ") and se.count("\n") == 1 and says in se, se


def test_a_map_of_another_machine_is_refused(files, tmp_path):
    tmp, _, _ = files
    code, _, se = run_cli(["map", "--machine", str(ROOT / "config" / "machines" /
                                                   "swivelhead_wcfxyzbt.yaml"),
                           "--map", str(tmp / "map.json"), "--predict",
                           str(tmp / "points.csv"), "--out", str(tmp_path / "o.csv")])
    assert code == 2 and "the map is of a WCBXFZYT machine" in se, se


CELL = st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(repr),
                 st.integers(-10**6, 10**6).map(str), st.text(max_size=8),
                 st.sampled_from(["", " ", "1e5", "-0", "1_0", "٣", "nan", "0x1", "1e999"]))


@settings(max_examples=120, deadline=None, suppress_health_check=[
    HealthCheck.function_scoped_fixture])
@given(st.lists(st.lists(CELL, min_size=0, max_size=4), max_size=6),
       st.sampled_from(["x_mm,y_mm,z_mm", "x_mm,y_mm", "X,Y,Z", ""]), st.booleans())
def test_fuzzed_points_files_never_end_in_a_traceback(files, tmp_path, rows, header, crlf):
    tmp, _, _ = files
    eol = "\r\n" if crlf else "\n"
    text = eol.join([header, *[",".join(r) for r in rows]]) + eol
    pts = tmp_path / "fuzz.csv"
    pts.write_bytes(text.encode("utf-8", "surrogatepass"))
    code, _, se = run_cli(["map", "--machine", str(MACHINE), "--map", str(tmp / "map.json"),
                           "--predict", str(pts), "--out", str(tmp_path / "o.csv")])
    assert code in (0, 2), (code, se, text)
    if code == 2:
        assert se.startswith("error: ") and se.count("\n") == 1, se


def test_a_chip_on_a_ball_is_left_out_of_the_map(files, tmp_path):
    """One equator touch latched 20 µm early (a chip): the daily check's outlier test leaves
    that ball visit out of the map and says so; the other centres are all used."""
    from dataclasses import replace

    from contracts.probing_log import read_log

    _, out, _ = files
    art = load_artefact(out[0][1])
    rows = list(read_log(out[0][0], art))
    k = next(i for i, r in enumerate(rows) if r.pose == 2 and r.ball == "B2" and r.touch == 1)
    r = rows[k]
    rows[k] = replace(r, x_mm=r.x_mm - r.dir_x * 0.02, y_mm=r.y_mm - r.dir_y * 0.02)
    write_log(tmp_path / "chip.csv", rows)
    code, _, se = run_cli(["map", "--machine", str(MACHINE), "--placement",
                            str(tmp_path / "chip.csv"), out[0][1], "--placement", *out[1],
                            "--max-degree", "2", "--json", str(tmp_path / "m.json")])
    assert code == 0, se
    doc = load_map(tmp_path / "m.json")
    assert doc.placements[0].centres == len(POSES) * 4 - 1
    assert any("measurement outlier at ball B2 pose 2" in w for w in doc.warnings), doc.warnings
