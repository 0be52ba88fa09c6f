"""The centres CSV contract (contracts/centres_file.py): round trip, preamble keys, and every
strictness rule as one error naming file, line and column."""

from __future__ import annotations

import io
import warnings
from pathlib import Path

import pytest

from benchmarks.rigs.reader_helpers import ARTEFACT, centre_rows
from contracts import centres_file
from contracts.centres_file import (
    HEADER,
    MAGIC,
    CentreRow,
    CentresFileError,
    read_centres,
    write_centres,
)
from contracts.probing_log import ProbeLogWarning


def _text(rows: list[CentreRow], **kw) -> str:
    buf = io.StringIO()
    write_centres(buf, rows, **kw)
    return buf.getvalue()


def _error(text: str) -> str:
    with pytest.raises(CentresFileError) as e:
        read_centres("c.csv", ARTEFACT, text=text)
    return str(e.value)


def test_round_trip_with_keys_and_comments(tmp_path: Path) -> None:
    rows = centre_rows()
    p = tmp_path / "c.csv"
    write_centres(p, rows, frame="instrument", instrument="CMM PMM-C 700", source="lab run 7",
                  repeatability_um=(0.3, 0.4, 0.2), comments=["calibrated 2024-05"])
    cf = read_centres(p, ARTEFACT)
    assert cf.rows == rows and cf.frame == "instrument" and cf.instrument == "CMM PMM-C 700"
    assert cf.source == "lab run 7" and cf.repeatability_um == (0.3, 0.4, 0.2)
    assert cf.comments == ["calibrated 2024-05"] and not cf.u_stated
    assert cf.lines == list(range(8, 16))  # magic, comment, 4 keys, header: rows from line 8
    stated = read_centres("c.csv", text=_text(centre_rows(u=0.5)))
    assert stated.u_stated and stated.column("u_um").tolist() == [0.5] * 8


def test_header_and_preamble_errors() -> None:
    good = _text(centre_rows())
    assert "line 1" in _error("# rumba-probing-log v1\n" + good.split("\n", 1)[1])
    assert "line 2: frame: expected one of machine, instrument" in _error(
        good.replace("# frame: machine", "# frame: cmm"))
    msg = _error(good.replace("# frame: machine", "# frame: machine\n# frame: machine"))
    assert "line 3: key 'frame' given twice" in msg
    msg = _error(good.replace("# frame: machine", "# frmae: instrument"))
    assert "line 2: expected '# key: value'" in msg and "frmae" in msg
    msg = _error(good.replace("# frame: machine", "# repeatability_um: 0.5,0,0.3"))
    assert "repeatability_um" in msg and "outside" in msg
    assert "expected the header" in _error(good.replace("u_um", "u"))
    assert "no centre rows" in _error(good.split("run-1")[0].rstrip(",\n0123456789.") + "\n")


@pytest.mark.parametrize(("old", "new", "want"), [
    ("-100.0,", "nan,", "column x_mm: expected a finite number, got 'nan'"),
    ("-100.0,", "-1٠0.0,", "column x_mm: expected a finite number"),
    ("-100.0,", "1e6,", "column x_mm: 1e6 outside [-100000, 100000]"),
    ("run-1,1,", "run-1,-1,", "column seq: expected an integer ≥ 0"),
    (",B1,", ",B9,", "unknown ball id 'B9'"),
    (",B1,", ",,", "column ball: expected an id"),
    ("152.125,\n", "152.125,0\n", "column u_um: 0 outside (0, 10000]"),
])
def test_cell_errors_name_line_and_column(old: str, new: str, want: str) -> None:
    msg = _error(_text(centre_rows()).replace(old, new, 1))
    assert want in msg and "c.csv: line " in msg


def test_ambiguous_data_is_refused_naming_both_lines() -> None:
    rows = centre_rows()
    text = _text(rows)
    lines = text.splitlines()
    first = len(lines) - 8  # the line of row 0 (1-based: index + 1)
    dup = "\n".join([*lines, lines[first].replace("run-1,1,", "run-1,99,")]) + "\n"
    assert f"ball B1 pose 0 repeat 0 run run-1 duplicates line {first + 1}" in _error(dup)
    seq = "\n".join([*lines, lines[first].replace(",0,0,0.0", ",1,0,0.0")]) + "\n"
    assert "seq 1 of run run-1 duplicates line" in _error(seq)
    other = text.replace("run-1,2,20.0,0,0,0.0,0.0", "run-1,2,20.0,0,0,0.0,5.0")
    assert "pose 0 commanded at b=0, c=5 but at b=0, c=0" in _error(other)
    mixed = text.replace("152.125,\n", "152.125,0.4\n", 1)
    assert "line 5: column u_um: empty, but stated on the first row" in _error(mixed)


def test_seq_gap_is_a_warning_and_ceilings(monkeypatch) -> None:
    rows = [r for r in centre_rows() if r.seq != 3]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        cf = read_centres("c.csv", ARTEFACT, text=_text(rows))
    assert len(cf.rows) == 7
    assert [str(w.message) for w in caught if w.category is ProbeLogWarning] == [
        "c.csv: run run-1: seq 3 missing (centres lost or rows deleted)"]
    assert "longer than 4096 bytes" in _error(_text(centre_rows()) + "#" * 5000 + "\n")
    monkeypatch.setattr(centres_file, "MAX_CENTRE_ROWS", 5)
    assert "more than 5 centre rows" in _error(_text(centre_rows()))


def test_header_constant_is_the_documented_contract() -> None:
    # the manual's "Centres file" documents exactly this line; a change is a new version
    assert MAGIC == "# rumba-centres v1"
    assert ",".join(HEADER) == ("run_id,seq,t_s,repeat,pose,b_cmd_deg,c_cmd_deg,b_deg,c_deg,"
                                "ball,x_mm,y_mm,z_mm,u_um")
    page = Path(__file__).resolve().parents[1] / "docs/reference/centres-file.md"
    assert ",".join(HEADER) in page.read_text(encoding="utf-8") and MAGIC in page.read_text(
        encoding="utf-8")
