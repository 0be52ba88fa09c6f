"""Inputs that once got through, at the readers: special files and over-long
files are refused at once, direction vectors must be directions, YAML keys are given once and
booleans are true/false, a NUL in an instrument file's comment and a '-0' counter are refused.
Everything here is contracts only (no daemon): one ``ConfigError`` line naming the file."""

from __future__ import annotations

import io
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

import contracts.centres_file as centres_file
import contracts.importers.common as importers_common
import contracts.probing_log as pl
from benchmarks.rigs.reader_helpers import ARTEFACT, CONFIG, centre_rows
from contracts.centres_file import CentresFileError, read_centres, write_centres
from contracts.importers import CentresImportError, import_centres
from contracts.input_files import bounded_lines
from contracts.probing_log import ProbeLogError, read_log
from contracts.setup_files import load_artefact, load_machine, load_plan
from contracts.yaml_files import ConfigError, read_yaml

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE_LOG = CONFIG / "examples/thesis_annexB_14poses.csv"
DATA = ROOT / "tests/data/centres"
READERS = {
    "log": "from contracts.probing_log import read_log as r; r(p)",
    "centres": "from contracts.centres_file import read_centres as r; r(p)",
    "auto": "from contracts.importers import import_centres as r; "
            "r(p, balls=['B1'], rotary=('B', 'C'), poses=[(0, 0)])",
    "kinopt": "from contracts.importers import import_centres as r; "
              "r(p, 'kinopt', balls=['B1'], rotary=('B', 'C'))",
    "dmis": "from contracts.importers import import_centres as r; "
            "r(p, 'dmis', balls=['B1'], rotary=('B', 'C'), poses=[(0, 0)])",
    "yaml": "from contracts.yaml_files import read_yaml as r; r(p)",
    "targets": "from programs.model import load_targets as r; r(p, None)",
}


def _child(reader: str, path: str, timeout: float = 20.0) -> tuple[int, str]:
    """Run one reader on ``path`` in a child with 1 GiB of memory: a hang (a FIFO) is a
    timeout and a runaway read (/dev/zero) a MemoryError there, not in the test run."""
    code = ("import resource, sys; resource.setrlimit(resource.RLIMIT_AS, (1 << 30, 1 << 30))\n"
            "from contracts.yaml_files import ConfigError\n"
            f"p = sys.argv[1]\ntry:\n    {READERS[reader]}\n"
            "except ConfigError as e:\n    print('refused:', e); sys.exit(2)\n")
    try:
        done = subprocess.run([sys.executable, "-c", code, path], cwd=ROOT, timeout=timeout,
                              capture_output=True, text=True)
    except subprocess.TimeoutExpired:
        return -1, "hang"
    return done.returncode, done.stdout + done.stderr


# ------------------------------------------------------------------ b. special, long files


@pytest.mark.parametrize("reader", sorted(READERS))
def test_fifo_device_and_directory_are_refused_at_once(reader: str, tmp_path: Path) -> None:
    fifo = tmp_path / "pipe.csv"
    os.mkfifo(fifo)
    for path, kind in [(str(fifo), "a FIFO"), ("/dev/zero", "a character device"),
                       (str(tmp_path), "a directory")]:
        rc, out = _child(reader, path)
        assert rc == 2, (reader, path, rc, out[-300:])  # not a hang, not a MemoryError
        assert out.strip().startswith(f"refused: {path}: is {kind}"), (reader, path, out)
        assert out.strip().endswith("expected a regular file"), out
        assert len(out.strip().splitlines()) == 1, out


def test_a_line_longer_than_the_limit_is_refused_without_reading_it_all() -> None:
    class Endless(io.RawIOBase):  # /dev/zero as a stream: no line break, no end
        read_bytes = 0

        def readable(self) -> bool:
            return True

        def readinto(self, b) -> int:  # type: ignore[override]
            b[:] = b"\0" * len(b)
            Endless.read_bytes += len(b)
            return len(b)

    lines = bounded_lines(io.BufferedReader(Endless()), "zero", ProbeLogError, 1 << 26, 4096)
    with pytest.raises(ProbeLogError, match=r"^zero: line 1: longer than 4096 bytes$"):
        next(lines)
    assert Endless.read_bytes < 1 << 20


def _big_log(path: Path, rows: int) -> None:
    head, first = EXAMPLE_LOG.read_text().splitlines()[:2], EXAMPLE_LOG.read_text().split(
        "\n")[2].split(",")
    with path.open("w") as f:
        f.write("\n".join(head) + "\n")
        for k in range(rows):
            first[1], first[3] = str(k + 1), str(k // 56)
            f.write(",".join(first) + "\n")


def test_an_over_long_log_is_refused_before_it_is_parsed(tmp_path: Path, monkeypatch) -> None:
    path = tmp_path / "long.csv"
    _big_log(path, pl.MAX_LOG_ROWS + 1)
    t0 = time.process_time()  # CPU seconds: the work, whatever else the box runs
    with pytest.raises(ProbeLogError) as info:
        read_log(path, ARTEFACT)
    took = time.process_time() - t0
    assert str(info.value) == (f"{path}: line {pl.MAX_LOG_ROWS + 3}: more than "
                               f"{pl.MAX_LOG_ROWS} touch rows (the reader's ceiling; one run "
                               "is far smaller)")
    assert took < 2.0, f"{took:.1f} CPU s to refuse {pl.MAX_LOG_ROWS + 1} rows"  # was 5 s (241 s)
    parsed = []  # and not a row was parsed: the count comes first
    monkeypatch.setattr(pl.ProbeLog, "_append", lambda self, *a: parsed.append(a))
    monkeypatch.setattr(pl, "MAX_LOG_ROWS", 10)
    small = tmp_path / "small.csv"
    _big_log(small, 11)
    with pytest.raises(ProbeLogError, match=r"line 13: more than 10 touch rows"):
        read_log(small, ARTEFACT)
    assert parsed == []


def test_over_long_centres_and_instrument_files_are_refused_before_parsing(
        tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr(centres_file, "MAX_CENTRE_ROWS", 5)
    cells = []
    monkeypatch.setattr(centres_file, "_cell", lambda *a: cells.append(a))
    p = tmp_path / "c.csv"
    write_centres(p, centre_rows(), comments=["a comment"])
    with pytest.raises(CentresFileError, match=r"c.csv: line 10: more than 5 centre rows"):
        read_centres(p)
    assert cells == []
    monkeypatch.setattr(importers_common, "MAX_IMPORT_LINES", 100)
    for sample, fmt in [("kinopt_B1.nc", "kinopt"), ("dmis_cmm.dmo", "dmis")]:
        with pytest.raises(CentresImportError, match=r"line \d+: more than 100 lines \(the "
                           r"importer's ceiling\)$"):
            import_centres(DATA / sample, fmt, balls=ARTEFACT.ids, rotary=("B", "C"),
                           ball="B1", poses=[(0.0, 0.0)] * 14)


# ------------------------------------------------------------------ c. directions


def _machine_doc() -> dict:
    return yaml.safe_load((CONFIG / "machines/thesis_wcbxfzyt.yaml").read_text())


@pytest.mark.parametrize(("where", "value"), [
    (("tool", "spindle_axis"), [0, 0, 0]), (("tool", "spindle_axis"), [0, 1e-12, 0]),
    (("axes", "X", "direction"), [0, 0, 0]), (("axes", "B", "direction"), [0.0, -0.0, 0.0]),
    (("gravity",), [0, 0, 0])])
def test_a_zero_direction_is_refused_naming_the_key(tmp_path: Path, where, value) -> None:
    doc = _machine_doc()
    node = doc
    for k in where[:-1]:
        node = node[k]
    node[where[-1]] = value
    p = tmp_path / "m.yaml"
    p.write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError) as info:
        load_machine(p)
    msg = str(info.value)
    assert msg.startswith(f"{p}: {'.'.join(where)}: must be a non-zero direction"), msg
    assert len(msg.splitlines()) == 1


def test_a_normalisable_spindle_axis_is_normalised(tmp_path: Path) -> None:
    doc = _machine_doc()
    doc["tool"]["spindle_axis"] = [0, 0, 7.5]
    p = tmp_path / "m.yaml"
    p.write_text(yaml.safe_dump(doc))
    m, _ = load_machine(p)
    assert m.spindle_axis == (0.0, 0.0, 1.0)


# ------------------------------------------------------------------ d. YAML keys and booleans


@pytest.mark.parametrize(("loader", "rel"), [
    (load_machine, "machines/thesis_wcbxfzyt.yaml"),
    (load_artefact, "artefacts/thesis_4ball.yaml"),
    (load_plan, "plans/shift_start_14poses.yaml")])
def test_a_duplicate_key_is_refused_naming_file_key_and_line(tmp_path: Path, loader,
                                                             rel: str) -> None:
    text = (CONFIG / rel).read_text()
    p = tmp_path / Path(rel).name
    p.write_text(text + "name: second\n")  # an edit appended below the old value
    with pytest.raises(ConfigError) as info:
        loader(p)
    first = next(n for n, line in enumerate(text.splitlines(), 1) if line.startswith("name:"))
    assert str(info.value) == (f"{p}: line {len(text.splitlines()) + 1}: key 'name' given "
                               f"twice (first on line {first}); a key is given once per "
                               "mapping")


def test_nested_and_flow_duplicates_are_refused_and_merge_keys_still_work(tmp_path) -> None:
    p = tmp_path / "x.yaml"
    for text, line in [("a:\n  b: 1\n  c: 2\n  b: 3\n", 4), ("a: [{k: 1, k: 2}]\n", 1),
                       ("1: a\n1.0: b\n", 2), ("a: 1\n'a': 2\n", 2)]:
        p.write_text(text)
        with pytest.raises(ConfigError, match=rf"^{p}: line {line}: key '.*' given twice"):
            read_yaml(p)
    p.write_text("base: &b {x: 1, y: 2}\nuse:\n  <<: *b\n  y: 3\n")
    assert read_yaml(p) == {"base": {"x": 1, "y": 2}, "use": {"x": 1, "y": 3}}


@pytest.mark.parametrize("value", ["'yes'", "yes", "on", "'true'", "1", "0", "~", "Yes", "y"])
def test_unattended_is_strictly_a_boolean(tmp_path: Path, value: str) -> None:
    text = (CONFIG / "machines/thesis_wcbxfzyt.yaml").read_text()
    assert "unattended: false" in text
    p = tmp_path / "m.yaml"
    p.write_text(text.replace("unattended: false", f"unattended: {value}"))
    with pytest.raises(ConfigError) as info:
        load_machine(p)
    assert "controller_kinematics.guards.unattended: expected true or false, got" in \
        str(info.value)
    for ok in ("true", "false", "True", "FALSE"):
        p.write_text(text.replace("unattended: false", f"unattended: {ok}"))
        _, mf = load_machine(p)
        assert mf.controller_kinematics.guards.unattended is (ok.lower() == "true")


def test_yaml_1_1_booleans_are_plain_strings(tmp_path: Path) -> None:
    p = tmp_path / "x.yaml"
    p.write_text("a: yes\nb: no\nc: on\nd: off\ne: true\nf: False\n")
    assert read_yaml(p) == {"a": "yes", "b": "no", "c": "on", "d": "off", "e": True,
                            "f": False}


# ------------------------------------------------------------------ e. NUL and '-0'


@pytest.mark.parametrize(("sample", "fmt", "marker", "comment"), [
    ("kinopt_B1.nc", "kinopt", "; Call cycle", "; Call\x00 cycle"),
    ("kinopt_B1.nc", "kinopt", "(X coordinate", "(X\x00 coordinate"),
    ("dmis_cmm.dmo", "dmis", "$$ datum plane", "$$ datum\x00 plane"),
    ("dmis_cmm.dmo", "dmis", "$$ DMIS results", "$$ DMIS\x1b[2J results")])
def test_a_control_character_in_an_instrument_comment_is_refused(tmp_path: Path, sample: str,
                                                                fmt: str, marker: str,
                                                                comment: str) -> None:
    text = (DATA / sample).read_text()
    line = next(n for n, x in enumerate(text.splitlines(), 1) if marker in x)
    p = tmp_path / sample
    p.write_text(text.replace(marker, comment, 1))
    for f in (fmt, "auto"):
        with pytest.raises(CentresImportError) as info:
            import_centres(p, f, balls=ARTEFACT.ids, rotary=("B", "C"), ball="B1",
                           poses=[(0.0, 0.0)] * 14)
        assert str(info.value).startswith(f"{p}: line {line}: column ")
        assert "control character" in str(info.value)


def test_a_control_character_in_a_centres_comment_is_refused(tmp_path: Path) -> None:
    p = tmp_path / "c.csv"
    write_centres(p, centre_rows(), comments=["serial 12\x00 34"])
    with pytest.raises(CentresFileError, match=rf"^{p}: line 2: a control character"):
        read_centres(p)


@pytest.mark.parametrize("col", ["seq", "repeat", "pose", "touch"])
@pytest.mark.parametrize("cell", ["-0", " -0 ", "-00", "-3"])
def test_a_minus_sign_on_a_counter_is_refused(tmp_path: Path, col: str, cell: str) -> None:
    lines = EXAMPLE_LOG.read_text().splitlines()
    cells = lines[6].split(",")
    cells[pl.HEADER.index(col)] = cell
    lines[6] = ",".join(cells)
    p = tmp_path / "log.csv"
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(ProbeLogError) as info:
        read_log(p, ARTEFACT)
    assert str(info.value) == (f"{p}: line 7: column {col}: expected an integer, got "
                               f"{cell!r} (ASCII digits, no sign, no leading zero, < 1e9)")


def test_a_minus_zero_in_a_centres_file_is_refused() -> None:
    buf = io.StringIO()
    write_centres(buf, centre_rows())
    text = buf.getvalue().replace("run-1,3,", "run-1,-0,", 1)
    with pytest.raises(CentresFileError, match=r"line \d+: column seq: expected an integer "
                       r"≥ 0, got '-0'"):
        read_centres("c.csv", text=text)
