"""The probing-log CSV contract: exact format, strict validation, touches → centres."""

from pathlib import Path

import numpy as np
import pytest

from contracts.probing_log import HEADER, MAGIC, ProbeLogError, ProbeLogWarning, read_log, write_log
from contracts.setup_files import load_artefact, load_machine
from daemon.analysis.touch_centres import rows_to_centres
from simulators.exact_log import Truth, make_rows, true_centres

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


# ------------------------------------------------------------------ strict numbers,
# seq, ceilings, encodings, numerical failures named by ball and pose


@pytest.mark.parametrize(("col", "value", "match"), [
    ("seq", "٣", r"line 7: column seq: expected an integer, got '٣'"),
    ("pose", "１", r"line 7: column pose: expected an integer, got '１'"),
    ("seq", "1_0", r"line 7: column seq: expected an integer, got '1_0'"),
    ("x_mm", "1_0.5", r"line 7: column x_mm: expected a finite number, got '1_0.5'"),
    ("x_mm", "٣.5", r"line 7: column x_mm: expected a finite number"),
    ("y_mm", "Infinity", r"line 7: column y_mm: expected a finite number"),
    ("z_mm", " nan ", r"line 7: column z_mm: expected a finite number"),
    ("x_mm", "1e15", r"line 7: column x_mm: 1e15 outside \[-100000, 100000\]"),
    ("y_mm", "-1e308", r"line 7: column y_mm: -1e308 outside"),
    ("z_mm", "1e999", r"line 7: column z_mm: 1e999 outside"),
    ("feed_mm_min", "-5", r"line 7: column feed_mm_min: -5 outside"),
    ("run_id", "a\x00b", r"line 7: column run_id: expected an id"),
])
def test_numbers_are_ascii_decimal_and_within_ceilings(setup, tmp_path, col, value,
                                                        match) -> None:
    _, a, _, rows = setup
    with pytest.raises(ProbeLogError, match=match):
        read_log(_corrupt(tmp_path, rows, 7, col, value), a)


def test_numbers_as_json_writes_them_are_accepted(setup, tmp_path) -> None:
    _, a, _, rows = setup
    for col, value in [("x_mm", "1.5e+2"), ("y_mm", "0.5"), ("z_mm", " -3.25 "),
                       ("x_mm", "-0"), ("y_mm", "1E-05"), ("seq", "5"), ("x_mm", "150")]:
        got = read_log(_corrupt(tmp_path, rows, 7, col, value), a)
        assert getattr(got[4], col) == float(value)


@pytest.mark.parametrize(("col", "value"), [
    ("x_mm", "+111.17"), ("y_mm", ".5"), ("z_mm", "-3."), ("x_mm", "007.5"), ("y_mm", "1.e3"),
    ("x_mm", "1 5"), ("seq", "+5"), ("seq", "05"), ("pose", "1e2")])
def test_numbers_outside_the_contracts_syntax_name_file_line_and_column(
        setup, tmp_path, col, value) -> None:
    # Python's float() reads '+111.17', '.5', '-3.' and '007.5': the contract does not
    _, a, _, rows = setup
    p = _corrupt(tmp_path, rows, 7, col, value)
    with pytest.raises(ProbeLogError) as info:
        read_log(p, a)
    kind = "a finite number" if col.endswith("_mm") else "an integer"
    assert str(info.value).startswith(f"{p}: line 7: column {col}: expected {kind}, got "), \
        info.value
    assert ("no '+', '.5', '5.' or leading zero" if col.endswith("_mm")
            else "no sign, no leading zero") in str(info.value)


def test_duplicated_seq_names_both_lines(setup, tmp_path) -> None:
    _, a, _, rows = setup
    p = _corrupt(tmp_path, rows, 9, "seq", str(rows[1].seq))  # line 4 holds rows[1]
    with pytest.raises(ProbeLogError, match=r"line 9: seq 2 of run synth duplicates line 4"):
        read_log(p, a)


def test_seq_gaps_are_a_warning_listing_the_missing_ranges(setup, tmp_path) -> None:
    _, a, _, rows = setup
    kept = [r for r in rows if r.seq not in (3, 10, 11, 12)]
    write_log(tmp_path / "gap.csv", kept)
    with pytest.warns(ProbeLogWarning, match=r"run synth: seq 3, 10–12 missing"):
        got = read_log(tmp_path / "gap.csv", a)
    assert len(got) == len(kept)


def test_ceilings_on_bytes_rows_and_line_length(setup, tmp_path, monkeypatch) -> None:
    import contracts.csv_lines as csv_lines  # the byte and line ceilings are read there
    import contracts.probing_log as pl

    _, a, _, rows = setup
    write_log(tmp_path / "log.csv", rows)
    size = (tmp_path / "log.csv").stat().st_size
    monkeypatch.setattr(csv_lines, "MAX_LOG_BYTES", size - 1)
    with pytest.raises(ProbeLogError, match=rf"{size} bytes, more than the reader's ceiling"):
        read_log(tmp_path / "log.csv", a)
    with pytest.raises(ProbeLogError, match=r"line 62: the log is larger than"):
        read_log("text", a, text=(tmp_path / "log.csv").read_text())
    monkeypatch.setattr(csv_lines, "MAX_LOG_BYTES", 10 * size)
    monkeypatch.setattr(pl, "MAX_LOG_ROWS", 10)
    with pytest.raises(ProbeLogError, match=r"line 13: more than 10 touch rows"):
        read_log(tmp_path / "log.csv", a)
    monkeypatch.setattr(pl, "MAX_LOG_ROWS", 10**6)
    p = _corrupt(tmp_path, rows, 8, "run_id", "r" * 5000)
    with pytest.raises(ProbeLogError, match=r"line 8: longer than 4096 bytes"):
        read_log(p, a)


def test_encodings_bom_crlf_and_bad_bytes(setup, tmp_path) -> None:
    _, a, _, rows = setup
    lines = _lines(tmp_path, rows)
    p = tmp_path / "crlf.csv"
    p.write_bytes(b"\xef\xbb\xbf" + "\r\n".join(lines).encode() + b"\r\n")
    assert read_log(p, a) == rows
    raw = "\n".join(lines).encode().split(b"\n")
    raw[10] = raw[10][:5] + b"\xff\xfe" + raw[10][5:]
    p.write_bytes(b"\n".join(raw))
    with pytest.raises(ProbeLogError, match=r"line 11: not UTF-8 text \(byte 6"):
        read_log(p, a)


def test_columns_are_compact_and_rows_compare_equal(setup, tmp_path) -> None:
    _, a, _, rows = setup
    write_log(tmp_path / "log.csv", rows)
    got = read_log(tmp_path / "log.csv", a)
    assert got == rows and rows == got and got[-1] == rows[-1] and got[:3] == rows[:3]
    assert got.column("x_mm").dtype == float and list(got.column("ball")[:5]) == ["B1"] * 5
    assert list(got.lines[:2]) == [3, 4]


def _moved(rows, pose: int, ball: str, fn) -> list:
    from dataclasses import replace

    out = []
    for r in rows:
        if r.pose == pose and r.ball == ball:
            x, y, z = fn(r)
            r = replace(r, x_mm=x, y_mm=y, z_mm=z)
        out.append(r)
    return out


@pytest.mark.parametrize(("fn", "what"), [
    (lambda r: (1.0, 2.0, 3.0), "degenerate"),  # all five touches at one point
    (lambda r: (r.touch * 1.0, r.touch * 2.0, r.touch * 3.0), "degenerate"),  # collinear
    (lambda r: (r.x_mm, r.y_mm, 7.0), "degenerate"),  # coplanar: the pole on the equator
    (lambda r: (1e308 * (-1) ** r.touch, 1e308, 0.0), "too large"),
    (lambda r: (1e15 + r.touch, 1e15, -1e15), ""),
    (lambda r: (float("nan"), 0.0, 0.0), "not finite"),
])
def test_numerical_failures_name_the_ball_and_pose(setup, fn, what) -> None:
    _, a, _, rows = setup
    bad = _moved(rows, 1, "B3", fn)
    with pytest.raises(ProbeLogError, match=rf"ball B3 pose 1 repeat 0: sphere fit failed: "
                                            rf".*{what}"):
        rows_to_centres(bad, a, 3.0, source="x.csv")


def test_probelog_errors_are_config_errors_the_cli_prints_as_one_line() -> None:
    from contracts.yaml_files import ConfigError

    assert issubclass(ProbeLogError, ConfigError)
