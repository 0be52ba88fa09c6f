"""Property-based fuzzing of the readers' surfaces: special files and row ceilings of every
reader, duplicate YAML keys, strict booleans, direction vectors, control characters in
instrument files, signed counters, and analyses against a wrong machine geometry.

Every example is classified: read, refused (one line naming the file), traceback (any other
exception), hang (``HANG_S`` CPU seconds without an answer, or blocked), wrong acceptance
(accepted although the input is wrong) or wrong refusal (a valid input refused); each test
asserts tracebacks, hangs and wrong acceptances (and wrong refusals) are 0, and prints its
counts (``pytest -s``)."""

from __future__ import annotations

import copy
import os
import re
import warnings
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import contracts.probing_log as pl
from benchmarks.rigs.input_fuzz_helpers import (
    DATA,
    EXAMPLE_LOG,
    READERS,
    SAMPLES,
    Tally,
    outcome,
    special_file,
)
from benchmarks.rigs.reader_helpers import ARTEFACT, CONFIG, centre_rows
from contracts.centres_file import read_centres, write_centres
from contracts.probing_log import read_log
from contracts.setup_files import load_artefact, load_machine, load_plan, machine_from_dict
from contracts.yaml_files import ConfigError, read_yaml
from daemon.analysis.identify import AnalysisError, analyse_centres
from daemon.analysis.touch_centres import rows_to_centres
from identification.plausibility import MAX_LINK_ROTATION_RAD, MAX_LINK_TRANSLATION_MM

GEOMETRY_EXAMPLES = 30  # an analysis takes about 0.3 s
FUZZ = settings(max_examples=60, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture,
                                       HealthCheck.too_slow])


def test_special_files_are_refused_without_hanging(tmp_path: Path) -> None:
    tally = Tally("special files")
    kinds = ["fifo", "link-to-fifo", "dir", "/dev/zero", "/dev/null", "/dev/urandom",
             "/dev/tty", "link-to-sample", "empty"]

    @FUZZ
    @given(reader=st.sampled_from(sorted(READERS)), kind=st.sampled_from(kinds))
    def run(reader: str, kind: str) -> None:
        if kind == "/dev/tty" and not os.path.exists(kind):
            kind = "/dev/null"
        path, may = special_file(tmp_path, kind, SAMPLES.get(reader))
        tally.add(outcome(lambda: READERS[reader](path), path, None if may else False),
                  (reader, kind))

    run()
    tally.verdict()


def _log_lines() -> tuple[list[str], str]:
    lines = EXAMPLE_LOG.read_text().splitlines()
    return lines[:2], lines[2]


def test_row_ceiling_counts_rows_not_lines(tmp_path: Path, monkeypatch) -> None:
    """Blank and blank-looking lines between rows do not count; one row too many is refused
    before any row is parsed."""
    tally = Tally("row ceiling")
    head, row = _log_lines()
    ceiling = 12
    monkeypatch.setattr(pl, "MAX_LOG_ROWS", ceiling)
    parsed = Counter[str]()
    real_append = pl.ProbeLog._append

    def counting(self: pl.ProbeLog, *a: Any) -> None:
        parsed["rows"] += 1
        real_append(self, *a)

    monkeypatch.setattr(pl.ProbeLog, "_append", counting)

    @FUZZ
    @given(n=st.integers(1, 2 * ceiling), fillers=st.lists(
        st.tuples(st.integers(0, 30), st.sampled_from(["", " ", "\t", " \t ", "   "])),
        max_size=8))
    def run(n: int, fillers: list[tuple[int, str]]) -> None:
        body = []
        for k in range(n):
            cells = row.split(",")
            cells[1], cells[8] = str(k + 1), str(k % 5 + 1)  # seq, touch
            cells[4] = str(k // 5)  # pose: one ball-pose per five touches
            body.append(",".join(cells))
        for at, filler in fillers:
            body.insert(at % (len(body) + 1), filler)
        path = tmp_path / "rows.csv"
        path.write_text("\n".join(head + body) + "\n")
        parsed.clear()
        result = outcome(lambda: read_log(path, ARTEFACT), path, None)
        over = n > ceiling
        if over and result[0] == "refused" and parsed["rows"]:
            result = ("wrong acceptance", f"{parsed['rows']} rows parsed before the refusal")
        elif over and result[0] == "read":
            result = ("wrong acceptance", f"{n} rows read, ceiling {ceiling}")
        tally.add(result, (n, fillers))

    run()
    tally.verdict()


# ------------------------------------------------------------------- YAML keys and booleans

YAML_FILES = {  # shipped file → loader
    "machines/thesis_wcbxfzyt.yaml": load_machine,
    "machines/linuxcnc_xyzbc.yaml": load_machine,
    "artefacts/thesis_4ball_scaled.yaml": load_artefact,
    "plans/shift_start_14poses.yaml": load_plan,
}
_KEY_LINE = re.compile(r"^(\s*)([A-Za-z_][A-Za-z0-9_]*):(.*)$")
_FLOW_ITEM = re.compile(r"([{,]\s*)([A-Za-z_][A-Za-z0-9_]*):\s*([^,{}\[\]]+?)(\s*[,}])")


def _block_key_lines(text: str) -> set[int]:
    """The lines where a key of a block-style mapping starts (not inside ``{…}``)."""
    out, stack = set(), [yaml.compose(text)]
    while stack:
        node = stack.pop()
        if isinstance(node, yaml.MappingNode):
            out |= {k.start_mark.line for k, _ in node.value if not node.flow_style}
            stack += [v for _, v in node.value]
        elif isinstance(node, yaml.SequenceNode):
            stack += node.value
    return out


def _duplicated(text: str, pick: int, flow: bool) -> str | None:
    """``text`` with one mapping key given twice: a block key line repeated below itself, or
    one item of a flow mapping repeated inside its braces (None when there is none)."""
    lines = text.splitlines()
    if flow:
        sites = [(n, m) for n, line in enumerate(lines) if not line.lstrip().startswith("#")
                 for m in _FLOW_ITEM.finditer(line.split(" #")[0])]
        if not sites:
            return None
        n, m = sites[pick % len(sites)]
        line = lines[n]
        lines[n] = (line[:m.end(3)] + f", {m.group(2)}: {m.group(3)}" + line[m.end(3):])
        return "\n".join(lines) + "\n"
    block = _block_key_lines(text)
    sites = [n for n, line in enumerate(lines) if _KEY_LINE.match(line) and n in block]
    n = sites[pick % len(sites)]
    indent = _KEY_LINE.match(lines[n]).group(1)  # type: ignore[union-attr]
    end = n + 1  # the key's block: the lines below it indented deeper
    while end < len(lines) and (not lines[end].strip() or lines[end].startswith(indent + " ")
                                or lines[end].lstrip().startswith("#")):
        end += 1
    return "\n".join(lines[:end] + lines[n:end] + lines[end:]) + "\n"


def test_a_duplicated_key_is_never_accepted(tmp_path: Path) -> None:
    tally = Tally("duplicate keys")

    @FUZZ
    @given(rel=st.sampled_from(sorted(YAML_FILES)), pick=st.integers(0, 10_000),
           flow=st.booleans())
    def run(rel: str, pick: int, flow: bool) -> None:
        text = _duplicated((CONFIG / rel).read_text(), pick, flow)
        if text is None:
            return
        path = tmp_path / Path(rel).name
        path.write_text(text)
        result = outcome(lambda: YAML_FILES[rel](path), path, False)
        if result[0] == "refused":
            try:
                read_yaml(path)
                result = ("wrong acceptance", "refused, but not as a duplicate key")
            except ConfigError as e:
                if "given twice" not in str(e):
                    result = ("wrong acceptance", f"refused for another reason: {e}")
        tally.add(result, (rel, pick, flow))

    run()
    tally.verdict()


BOOL_SITES = {  # shipped file, its text, the YAML text of a boolean key to replace
    "unattended": ("machines/thesis_wcbxfzyt.yaml", "unattended: false"),
    "drift_check": ("plans/shift_start_14poses.yaml", "drift_check: true"),
}
_YAML_BOOLS = {"true", "True", "TRUE", "false", "False", "FALSE"}
_BOOLISH = st.one_of(
    st.sampled_from([*sorted(_YAML_BOOLS), "yes", "no", "on", "off", "y", "n", "Yes", "NO",
                                           "'true'", "'yes'", '"false"', "1", "0", "-1",
                                           "1.0", "~", "null", "''", "[]", "{}", "[true]",
                                           "!!bool yes", "!!bool maybe", "!!bool true",
                                           "!!str true", "!!int 1", "!!binary x",
                                           "!!timestamp 2020-13-45", "tRUE", ".nan"]),
    st.integers(-5, 5).map(str), st.text("tTrRuUeEfFaAlLsSyYnNoO01 '", max_size=6))


def test_a_boolean_key_takes_only_true_or_false(tmp_path: Path) -> None:
    tally = Tally("strict booleans")

    @FUZZ
    @given(site=st.sampled_from(sorted(BOOL_SITES)), value=_BOOLISH)
    def run(site: str, value: str) -> None:
        rel, key_text = BOOL_SITES[site]
        text = (CONFIG / rel).read_text()
        assert key_text in text
        path = tmp_path / Path(rel).name
        path.write_text(text.replace(key_text, f"{site}: {value}"))
        valid = value.strip().removeprefix("!!bool ") in _YAML_BOOLS
        tally.add(outcome(lambda: YAML_FILES[rel](path), path, valid), (site, value))

    run()
    tally.verdict()


# ------------------------------------------------------------------- direction vectors

_COMPONENT = st.one_of(st.sampled_from([0.0, -0.0, 1.0, -1.0, 1e-12, 1e-10, 2.0, 1e5, 1e6]),
                       st.floats(-2.0, 2.0), st.floats(allow_nan=True, allow_infinity=True))


def test_a_direction_is_refused_unless_it_is_one(tmp_path: Path) -> None:
    tally = Tally("directions")
    base = yaml.safe_load((CONFIG / "machines/thesis_wcbxfzyt.yaml").read_text())

    @FUZZ
    @given(site=st.sampled_from(["spindle_axis", "X", "B", "gravity"]),
           v=st.lists(_COMPONENT, min_size=3, max_size=3))
    def run(site: str, v: list[float]) -> None:
        doc = copy.deepcopy(base)
        if site == "spindle_axis":
            doc["tool"]["spindle_axis"] = v
        elif site == "gravity":
            doc["gravity"] = v
        else:
            doc["axes"][site]["direction"] = v
        path = tmp_path / "m.yaml"
        path.write_text(yaml.safe_dump(doc))
        a = np.asarray(v, float)
        with np.errstate(all="ignore"):
            norm = float(np.linalg.norm(a)) if np.isfinite(a).all() else float("nan")
        zero = not np.isfinite(a).all() or np.abs(a).max() > 1e5 or not norm >= 1e-9

        def check(out: Any) -> bool:
            m, _ = out
            s = np.asarray(m.spindle_axis, float)
            return bool(np.isfinite(s).all() and abs(np.linalg.norm(s) - 1.0) < 1e-9)

        tally.add(outcome(lambda: load_machine(path), path, False if zero else None, check),
                  (site, v))

    run()
    tally.verdict()


# ------------------------------------------------------------------- control chars, counters

_CONTROL = st.sampled_from([chr(c) for c in [*range(0, 9), 11, 12, *range(14, 32), 127]])


def test_a_control_character_in_an_instrument_file_is_never_accepted(tmp_path: Path) -> None:
    tally = Tally("control characters")

    @FUZZ
    @given(sample=st.sampled_from(["kinopt_B1.nc", "dmis_cmm.dmo"]),
           line=st.integers(0, 10_000), col=st.integers(0, 200), ch=_CONTROL,
           fmt=st.sampled_from(["own", "auto"]))
    def run(sample: str, line: int, col: int, ch: str, fmt: str) -> None:
        lines = (DATA / sample).read_text().split("\n")
        k = line % len(lines)
        c = col % (len(lines[k]) + 1)
        lines[k] = lines[k][:c] + ch + lines[k][c:]
        path = tmp_path / sample
        path.write_text("\n".join(lines), encoding="utf-8")
        reader = READERS["auto" if fmt == "auto" else sample.split("_")[0]]
        tally.add(outcome(lambda: reader(path), path, False), (sample, k, c, ch, fmt))

    run()
    tally.verdict()


_COUNTER = st.one_of(st.sampled_from(["-0", "+0", "-00", " -0", "-0 ", "0", "+1", "-1", "1",
                                      "--1", "+-1", "- 0", "0-", "1e0", "٠", "0x1", ""]),
                     st.integers(-10, 10).map(str), st.text("+-0123 ", max_size=5))


def test_a_signed_counter_is_never_accepted(tmp_path: Path) -> None:
    tally = Tally("counters")
    lines = EXAMPLE_LOG.read_text().splitlines()

    @FUZZ
    @given(kind=st.sampled_from(["log", "centres"]), line=st.integers(2, 50),
           col=st.sampled_from(["seq", "repeat", "pose", "touch"]), cell=_COUNTER)
    def run(kind: str, line: int, col: str, cell: str) -> None:
        if kind == "log":
            body = list(lines)
            cells = body[line].split(",")
            cells[pl.HEADER.index(col)] = cell
            body[line] = ",".join(cells)
            path = tmp_path / "log.csv"
            path.write_text("\n".join(body) + "\n")
            call: Callable[[], Any] = lambda: read_log(path, ARTEFACT)  # noqa: E731
        else:
            if col == "touch":
                col = "seq"
            path = tmp_path / "c.csv"
            write_centres(path, centre_rows())
            text = path.read_text().split("\n")
            k = 3 + line % 8
            cells = text[k].split(",")
            cells[["run_id", "seq", "t_s", "repeat", "pose"].index(col)] = cell
            text[k] = ",".join(cells)
            path.write_text("\n".join(text))
            call = lambda: read_centres(path)  # noqa: E731
        signed = "-" in cell
        tally.add(outcome(call, path, False if signed else None), (kind, line, col, cell))

    run()
    tally.verdict()


# ------------------------------------------------------------------- wrong machine geometry


@pytest.fixture(scope="module")
def example_centres() -> Any:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return rows_to_centres(read_log(EXAMPLE_LOG, ARTEFACT), ARTEFACT, 3.0)


def test_an_analysis_against_a_wrong_geometry_is_refused(tmp_path: Path,
                                                         example_centres: Any) -> None:
    """The shipped example log (thesis machine) against the thesis machine file with a sign
    flipped, a rotary pivot or the tool tip moved: a gross change (a sign, ≥ 30 mm across the
    axis) must be refused, a small one (≤ 2 mm, absorbed as plausible link and setup errors)
    accepted; in between either (what absorbs the change decides)."""
    tally = Tally("wrong geometry")
    base = yaml.safe_load((CONFIG / "machines/thesis_wcbxfzyt.yaml").read_text())

    @settings(max_examples=GEOMETRY_EXAMPLES, deadline=None, derandomize=True, database=None,
              suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
    @given(change=st.sampled_from(["sign", "pivot B", "pivot C", "tip"]),
           axis=st.sampled_from("XYZBC"), mm=st.one_of(st.floats(0.0, 2.0),
                                                       st.floats(30.0, 500.0)),
           direction=st.lists(st.floats(-1, 1), min_size=3, max_size=3).filter(
               lambda v: np.linalg.norm(v) > 0.1))
    def run(change: str, axis: str, mm: float, direction: list[float]) -> None:
        doc = copy.deepcopy(base)
        d = np.asarray(direction) / np.linalg.norm(direction) * mm
        moved = mm
        if change == "sign":
            doc["axes"][axis]["sign"] = -doc["axes"][axis].get("sign", 1)
        elif change == "tip":
            doc["tool"]["tip_mm"] = [float(x) for x in np.add(doc["tool"]["tip_mm"], d)]
        else:
            ax = doc["axes"][change[-1]]
            ax["point_mm"] = [float(x) for x in np.add(ax["point_mm"], d)]
            a = np.asarray(ax["direction"], float)  # a pivot moved along its own axis is the
            moved = float(np.linalg.norm(d - (d @ a) * a))  # same axis: only the rest counts
        machine, _ = machine_from_dict(doc, "m.yaml")
        gross = change == "sign" or moved >= 30.0
        small = change != "sign" and mm <= 2.0

        def call() -> Any:
            try:
                return analyse_centres(machine, ARTEFACT, example_centres, source="m.yaml")
            except AnalysisError as e:
                raise ConfigError(str(e)) from None

        def check(out: Any) -> bool:  # an accepted fit stays within the plausible bounds
            return all(abs(v.value) * 1e-6 <= MAX_LINK_ROTATION_RAD if v.unit == "urad" else
                       abs(v.value) * 1e-3 <= MAX_LINK_TRANSLATION_MM
                       for v in out.links.values())

        tally.add(outcome(call, "m.yaml", False if gross else (True if small else None),
                           check), (change, axis, round(mm, 3), [round(x, 3) for x in d]))

    run()
    tally.verdict()
