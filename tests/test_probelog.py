"""The probing-log CSV contract: exact format, strict validation, touches → centres."""

from pathlib import Path

import numpy as np
import pytest

from daemon.config import load_artefact, load_machine
from daemon.probelog import (
    HEADER,
    MAGIC,
    ProbeLogError,
    ProbeLogWarning,
    read_log,
    rows_to_centres,
    write_log,
)
from tests.synth import Truth, make_rows, true_centres

CFG = Path(__file__).resolve().parents[1] / "config"
POSES = [(0.0, 0.0), (30.0, 60.0), (-30.0, 240.0)]


@pytest.fixture(scope="module")
def setup():
    m, _ = load_machine(CFG / "machines/thesis_wcbxfzyt.yaml")
    a = load_artefact(CFG / "artefacts/thesis_4ball.yaml")
    truth = Truth({"EX0C": -0.1}, np.full((4, 3), 0.2), np.array([0.1, 0.0, -0.1]))
    return m, a, truth, make_rows(m, a, POSES, truth)


def _lines(tmp_path: Path, rows) -> list[str]:
    write_log(tmp_path / "log.csv", rows)
    return (tmp_path / "log.csv").read_text().splitlines()


def test_exact_format_and_round_trip(setup, tmp_path: Path) -> None:
    _, a, _, rows = setup
    lines = _lines(tmp_path, rows)
    assert lines[0] == "# rumba-probing-log v1" == MAGIC
    assert lines[1] == ("run_id,seq,t_s,repeat,pose,b_cmd_deg,c_cmd_deg,ball,touch,dir_x,dir_y,"
                        "dir_z,x_mm,y_mm,z_mm,b_deg,c_deg,feed_mm_min")
    assert lines[1].split(",") == HEADER
    assert len(lines) == 2 + len(POSES) * 4 * 5
    assert read_log(tmp_path / "log.csv", a) == rows  # floats written shortest-round-trip


def test_centres_are_exact_without_noise(setup) -> None:
    m, a, truth, rows = setup
    d = rows_to_centres(rows, a, 3.0)
    want = true_centres(m, a, POSES, truth).reshape(-1, 3)
    assert np.abs(d.centres.xyz_mm - want).max() < 1e-9
    assert list(d.centres.pose) == [0] * 4 + [1] * 4 + [2] * 4
    assert list(d.centres.ball) == [0, 1, 2, 3] * 3
    assert max(abs(h.radius_dev_um) for h in d.health) < 1e-6
    assert max(h.form_rms_um for h in d.health) < 1e-6
    # With the wrong stylus the health figure shows it: 0.5 mm radius difference.
    d2 = rows_to_centres(rows, a, 2.5)
    assert d2.health[0].radius_dev_um == pytest.approx(500.0, abs=1e-6)


def _corrupt(tmp_path: Path, rows, line: int, col: str, value: str) -> Path:
    lines = _lines(tmp_path, rows)
    cells = lines[line - 1].split(",")
    cells[HEADER.index(col)] = value
    lines[line - 1] = ",".join(cells)
    p = tmp_path / "bad.csv"
    p.write_text("\n".join(lines) + "\n")
    return p


@pytest.mark.parametrize(("col", "value", "match"), [
    ("x_mm", "abc", r"line 7: column x_mm: expected a finite number, got 'abc'"),
    ("y_mm", "nan", r"line 7: column y_mm: expected a finite number"),
    ("z_mm", "inf", r"line 7: column z_mm: expected a finite number"),
    ("touch", "6", r"line 7: column touch: 6 outside 1..5"),
    ("touch", "1.5", r"line 7: column touch: expected an integer"),
    ("ball", "B9", r"line 7: column ball: unknown ball id 'B9'"),
])
def test_bad_cells_name_file_line_and_column(setup, tmp_path, col, value, match) -> None:
    _, a, _, rows = setup
    p = _corrupt(tmp_path, rows, 7, col, value)
    with pytest.raises(ProbeLogError, match=match) as e:
        read_log(p, a)
    assert str(p) in str(e.value)


def test_structure_errors(setup, tmp_path: Path) -> None:
    _, a, _, rows = setup
    lines = _lines(tmp_path, rows)
    p = tmp_path / "b.csv"
    p.write_text("\n".join(lines[1:]))
    with pytest.raises(ProbeLogError, match="line 1: expected '# rumba-probing-log v1'"):
        read_log(p, a)
    p.write_text("\n".join([lines[0], lines[1].replace("x_mm", "x"), *lines[2:]]))
    with pytest.raises(ProbeLogError, match="line 2: expected the header"):
        read_log(p, a)
    p.write_text("\n".join([*lines[:5], lines[5] + ",1", *lines[6:]]))
    with pytest.raises(ProbeLogError, match="line 6: expected 18 columns, got 19"):
        read_log(p, a)
    p.write_text("\n".join(lines[:2]))
    with pytest.raises(ProbeLogError, match="no touch rows"):
        read_log(p, a)


def test_duplicated_touch_is_an_error(setup, tmp_path: Path) -> None:
    _, a, _, rows = setup
    lines = _lines(tmp_path, rows)
    p = tmp_path / "dup.csv"
    p.write_text("\n".join([*lines, lines[4]]))
    with pytest.raises(ProbeLogError, match=r"line 63: touch 3 of ball B1 pose 0 .*duplicates "
                                            r"line 5"):
        read_log(p, a)


def test_incomplete_ball_pose_is_dropped_with_a_named_warning(setup) -> None:
    _, a, _, rows = setup
    short = [r for r in rows if not (r.pose == 1 and r.ball == "B2" and r.touch == 5)]
    with pytest.warns(ProbeLogWarning, match=r"ball B2 pose 1 repeat 0: only touches "
                                             r"\[1, 2, 3, 4\]"):
        d = rows_to_centres(short, a, 3.0)
    assert len(d.centres) == 11 and len(d.warnings) == 1
    assert not np.any((d.centres.pose == 1) & (d.centres.ball == 1))


def test_mixed_runs_and_moving_rotary_are_errors(setup) -> None:
    _, a, _, rows = setup
    other = [r.__class__(**{**r.__dict__, "run_id": "other"}) for r in rows[:5]]
    with pytest.raises(ProbeLogError, match="contains runs"):
        rows_to_centres(rows + other, a, 3.0)
    moved = list(rows)
    moved[2] = moved[2].__class__(**{**moved[2].__dict__, "c_deg": 0.5})
    with pytest.raises(ProbeLogError, match="rotary axes moved"):
        rows_to_centres(moved, a, 3.0)
