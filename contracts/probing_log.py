"""The probing-log CSV (DESIGN.md contract): read and validate, write.

Format: first line ``# rumba-probing-log v1``, then the header ``HEADER``, one row per touch.
Reading is strict: a malformed row, a number not written as JSON writes one (``+1.5``, ``.5``,
``1_0``, ``٣``, ``nan`` and ``inf`` are refused: ``FLOAT_RE``), a coordinate beyond its ceiling,
an unknown ball id, a touch outside 1..5, a duplicated (run, repeat, pose, ball, touch) or a
duplicated (run, seq) is a ``ProbeLogError`` naming file, line and column — the data are
ambiguous and nothing can be guessed. A ball-pose with fewer than five touches (an aborted run)
is dropped with a ``ProbeLogWarning``: the other groups are complete and the estimator itself
reports whether what is left is still enough. Gaps in ``seq`` (hits lost in transfer,
untriggered touches the daemon leaves out of an export, rows deleted by hand) are a
``ProbeLogWarning`` listing the missing ranges: every row names its own pose, ball and touch, so
the touches present are unaffected and the ball-poses the lost ones belonged to are dropped (and
named) as incomplete.

Ceilings (a log beyond them is refused with one line, before it can exhaust memory or time):
``MAX_LOG_BYTES`` = 64 MiB per file, ``MAX_LOG_ROWS`` = 250 000 touch rows (100 repeats of a
49-pose × 4-ball plan is 98 000), ``MAX_LINE_BYTES`` = 4 096 bytes per line, ``MAX_ABS_MM`` =
1e5 mm on x/y/z (no machine is 100 m long), ``MAX_ABS_DEG`` = 1e5° on the rotary columns,
|dir| ≤ 10, 0 ≤ t_s ≤ 1e8 s, 0 ≤ feed ≤ 1e6 mm/min, integers < 1e9, ids ≤ 200 characters.
``t_s`` ("seconds since run start", DESIGN.md) is, in the daemon's logs, seconds since the run's
first program started, on one clock for every program of the run (``contracts.jobs.RunClock``:
a re-probe round's rows follow the plan's, by the time that passed).
The reader streams the file line by line and keeps the rows in typed columns (``ProbeLog``,
about 150 bytes a row), so memory does not depend on the text's size.
"""

from __future__ import annotations

import csv
import io
import re
import warnings
from array import array
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import astuple, dataclass, fields
from pathlib import Path
from typing import overload

import numpy as np

from contracts.csv_lines import (  # noqa: F401 (re-exported: the log's public helpers)
    CONTROL_RE,
    MAX_LINE_BYTES,
    MAX_LOG_BYTES,
    ProbeLogError,
    ProbeLogWarning,
    byte_lines,
    data_rows,
    decoded,
    duplicate_key,
    seq_gaps,
)
from contracts.result_lines import MAX_RESULT_DEG, MAX_RESULT_MM
from identification.model import Artefact

MAGIC = "# rumba-probing-log v1"
HEADER = ["run_id", "seq", "t_s", "repeat", "pose", "b_cmd_deg", "c_cmd_deg", "ball", "touch",
          "dir_x", "dir_y", "dir_z", "x_mm", "y_mm", "z_mm", "b_deg", "c_deg", "feed_mm_min"]
TOUCHES_PER_BALL = 5
ROTARY_SPREAD_DEG = 0.01  # latched B/C of the five touches of one group must agree this well
MAX_LOG_ROWS = 250_000
MAX_ID_CHARS = 200
MAX_ABS_MM, MAX_ABS_DEG = MAX_RESULT_MM, MAX_RESULT_DEG  # one definition: contracts.result_lines
# (low, high) per float column; NaN fails every comparison, so it is refused as well
RANGES = {"t_s": (0.0, 1e8), "b_cmd_deg": (-MAX_ABS_DEG, MAX_ABS_DEG),
          "c_cmd_deg": (-MAX_ABS_DEG, MAX_ABS_DEG), "b_deg": (-MAX_ABS_DEG, MAX_ABS_DEG),
          "c_deg": (-MAX_ABS_DEG, MAX_ABS_DEG), "dir_x": (-10.0, 10.0),
          "dir_y": (-10.0, 10.0), "dir_z": (-10.0, 10.0), "x_mm": (-MAX_ABS_MM, MAX_ABS_MM),
          "y_mm": (-MAX_ABS_MM, MAX_ABS_MM), "z_mm": (-MAX_ABS_MM, MAX_ABS_MM),
          "feed_mm_min": (0.0, 1e6)}
# The contract's numbers are written as JSON writes them (RFC 8259 §6), in ASCII, blanks
# around allowed: an optional minus, digits without a leading zero, an optional fraction, an
# optional exponent — what rumba's writer (Python's repr) and spreadsheets produce. Nothing
# else: not '+111.17', '.5', '5.', '007', '1_0', '٣' or '１' (Python's float() takes them all),
# nor 'nan' or 'inf'. The integer columns (seq, repeat, pose, touch) are counters ≥ 0: no sign
# at all, so a '-0' (which int() reads as 0) cannot pass for a counter.
INT_RE = re.compile(r"[ \t]*(?:0|[1-9][0-9]{0,8})[ \t]*")
FLOAT_RE = re.compile(r"[ \t]*-?(?:0|[1-9][0-9]*)(?:\.[0-9]+)?(?:[eE][+-]?[0-9]{1,3})?[ \t]*")
NUMBER_SYNTAX = ("ASCII decimal as JSON writes it: -12.5, 0.25, 1e-05; no '+', '.5', '5.' or "
                 "leading zero")
COUNT_SYNTAX = "ASCII digits, no sign, no leading zero, < 1e9"
_ROWS_WHAT = "touch rows (the reader's ceiling; one run is far smaller)"


@dataclass(frozen=True)
class PoseRow:
    """The columns a touch row and a centre row (``contracts.centres_file``) start with."""

    run_id: str
    seq: int
    t_s: float
    repeat: int
    pose: int
    b_cmd_deg: float
    c_cmd_deg: float


@dataclass(frozen=True)
class LogRow(PoseRow):
    """One touch as in the CSV (columns in the same order)."""

    ball: str
    touch: int
    dir_x: float
    dir_y: float
    dir_z: float
    x_mm: float
    y_mm: float
    z_mm: float
    b_deg: float
    c_deg: float
    feed_mm_min: float


COLUMN_TYPES = {f.name: f.type for f in fields(LogRow)}
_STR_COLS = [i for i, h in enumerate(HEADER) if COLUMN_TYPES[h] == "str"]
_INT_COLS = [i for i, h in enumerate(HEADER) if COLUMN_TYPES[h] == "int"]
_FLOAT_COLS = [i for i, h in enumerate(HEADER) if COLUMN_TYPES[h] == "float"]
_FLOAT_RANGES = [RANGES[HEADER[i]] for i in _FLOAT_COLS]


class ProbeLog(Sequence[LogRow]):
    """The rows of a log, stored by column (run/ball as codes, numbers in typed arrays): a
    read-only sequence of ``LogRow`` (made on access) that compares equal to a list of the
    same rows; ``column(name)`` gives one column as a numpy array."""

    __slots__ = ("_codes", "_floats", "_ints", "_names", "lines")

    def __init__(self) -> None:
        self._names: dict[int, list[str]] = {i: [] for i in _STR_COLS}  # code → text
        self._codes: dict[int, array] = {i: array("l") for i in _STR_COLS}
        self._ints: dict[int, array] = {i: array("q") for i in _INT_COLS}
        self._floats: dict[int, array] = {i: array("d") for i in _FLOAT_COLS}
        self.lines = array("q")  # the file line of each row

    def _append(self, strs: Sequence[str], ints: Sequence[int], floats: Sequence[float],
                line: int, lookup: dict[int, dict[str, int]]) -> None:
        for i, s in zip(_STR_COLS, strs, strict=True):
            code = lookup[i].get(s)
            if code is None:
                code = lookup[i][s] = len(self._names[i])
                self._names[i].append(s)
            self._codes[i].append(code)
        for i, v in zip(_INT_COLS, ints, strict=True):
            self._ints[i].append(v)
        for i, v in zip(_FLOAT_COLS, floats, strict=True):
            self._floats[i].append(v)
        self.lines.append(line)

    def __len__(self) -> int:
        return len(self.lines)

    def _row(self, k: int) -> LogRow:
        vals: list[object] = [None] * len(HEADER)
        for i in _STR_COLS:
            vals[i] = self._names[i][self._codes[i][k]]
        for i in _INT_COLS:
            vals[i] = self._ints[i][k]
        for i in _FLOAT_COLS:
            vals[i] = self._floats[i][k]
        return LogRow(*vals)

    @overload
    def __getitem__(self, k: int) -> LogRow: ...

    @overload
    def __getitem__(self, k: slice) -> list[LogRow]: ...

    def __getitem__(self, k: int | slice) -> LogRow | list[LogRow]:
        if isinstance(k, slice):
            return [self._row(j) for j in range(*k.indices(len(self)))]
        if k < 0:
            k += len(self)
        if not 0 <= k < len(self):
            raise IndexError("probing-log row index out of range")
        return self._row(k)

    def __iter__(self) -> Iterator[LogRow]:
        for k in range(len(self)):
            yield self._row(k)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Sequence) or isinstance(other, str):
            return NotImplemented
        return len(self) == len(other) and all(a == b for a, b in zip(self, other, strict=True))

    __hash__ = None  # type: ignore[assignment]  # mutable while reading, like a list

    def __repr__(self) -> str:
        return f"ProbeLog({len(self)} rows)"

    def column(self, name: str) -> np.ndarray:
        """One column as a numpy array (strings as an object array)."""
        i = HEADER.index(name)
        if i in self._floats:
            return np.frombuffer(self._floats[i], float).copy()
        if i in self._ints:
            return np.frombuffer(self._ints[i], np.int64).copy()
        names = np.array(self._names[i] + [""], object)[:-1]
        return names[np.frombuffer(self._codes[i], np.dtype("l"))]


def _bad_cell(name: str, lineno: int, cells: Sequence[str]) -> ProbeLogError:
    """The slow path: the first cell that does not parse, named by its column."""
    for i, (col, cell) in enumerate(zip(HEADER, cells, strict=True)):
        if i in _STR_COLS:
            s = cell.strip()
            if not s and col == "run_id":
                return ProbeLogError(f"{name}: line {lineno}: column run_id: empty")
            if len(s) > MAX_ID_CHARS or CONTROL_RE.search(s):
                return ProbeLogError(f"{name}: line {lineno}: column {col}: expected an id of "
                                     f"at most {MAX_ID_CHARS} printable characters, "
                                     f"got {s[:40]!r}")
        elif i in _INT_COLS:
            if not INT_RE.fullmatch(cell):
                return ProbeLogError(f"{name}: line {lineno}: column {col}: expected an "
                                     f"integer, got {cell[:40]!r} ({COUNT_SYNTAX})")
        else:
            lo, hi = RANGES[col]
            if not FLOAT_RE.fullmatch(cell):
                return ProbeLogError(f"{name}: line {lineno}: column {col}: expected a finite "
                                     f"number, got {cell[:40]!r} ({NUMBER_SYNTAX})")
            if not lo <= float(cell) <= hi:
                return ProbeLogError(f"{name}: line {lineno}: column {col}: {cell.strip()} "
                                     f"outside [{lo:g}, {hi:g}]")
    return ProbeLogError(f"{name}: line {lineno}: cannot be read")  # not reached


def _check_keys(log: ProbeLog, name: str) -> None:
    """Duplicated touches or seq numbers are errors; seq gaps a warning (see module doc)."""
    run = np.frombuffer(log._codes[0], np.dtype("l")).astype(np.int64)
    ball = np.frombuffer(log._codes[HEADER.index("ball")], np.dtype("l")).astype(np.int64)
    col = {c: log.column(c) for c in ("seq", "repeat", "pose", "touch")}
    lines = np.frombuffer(log.lines, np.int64)
    dup = duplicate_key(np.stack([run, col["repeat"], col["pose"], ball, col["touch"]], 1), lines)
    if dup is not None:
        r = log[int(np.flatnonzero(lines == dup[1])[0])]
        raise ProbeLogError(f"{name}: line {dup[1]}: touch {r.touch} of ball {r.ball} pose "
                            f"{r.pose} repeat {r.repeat} run {r.run_id} duplicates line "
                            f"{dup[0]}")
    dup = duplicate_key(np.stack([run, col["seq"]], 1), lines)
    if dup is not None:
        r = log[int(np.flatnonzero(lines == dup[1])[0])]
        raise ProbeLogError(f"{name}: line {dup[1]}: seq {r.seq} of run {r.run_id} duplicates "
                            f"line {dup[0]} (two touches cannot share a sequence number)")
    for code, run_id in enumerate(log._names[0]):
        shown = seq_gaps(col["seq"][run == code])
        if shown:
            warnings.warn(f"{name}: run {run_id}: seq {shown} missing (touches lost in "
                          "transfer, not triggered, or rows deleted); the ball-poses they "
                          "belong to are incomplete and left out", ProbeLogWarning, stacklevel=3)


def read_log(path: Path | str, artefact: Artefact | None = None,
             text: str | None = None) -> ProbeLog:
    """Read and validate a probing log (``text`` instead of the file content if given)."""
    with byte_lines(path, text, note=" (one run is far smaller)",
                    rows=(MAX_LOG_ROWS, _ROWS_WHAT)) as raw:
        return _read(raw, str(path), artefact)


def _read(raw: Iterable[bytes], name: str, artefact: Artefact | None) -> ProbeLog:
    reader = csv.reader(decoded(raw, name, printable=True))
    try:
        first = next(reader, [])
        if len(first) != 1 or first[0].strip() != MAGIC:
            raise ProbeLogError(f"{name}: line 1: expected {MAGIC!r} (not a rumba probing "
                                "log?)")
        if [h.strip() for h in next(reader, [])] != HEADER:
            raise ProbeLogError(f"{name}: line 2: expected the header {','.join(HEADER)}")
        log = _rows(reader, name, artefact)
    except csv.Error as e:
        raise ProbeLogError(f"{name}: line {reader.line_num}: not CSV: {e}") from None
    if not len(log):
        raise ProbeLogError(f"{name}: no touch rows after the header")
    _check_keys(log, name)
    return log


def _rows(reader: Iterator[list[str]], name: str, artefact: Artefact | None) -> ProbeLog:
    ids = set(artefact.ids) if artefact is not None else None
    log = ProbeLog()
    lookup: dict[int, dict[str, int]] = {i: {} for i in _STR_COLS}
    int_m, float_m, ctrl = INT_RE.fullmatch, FLOAT_RE.fullmatch, CONTROL_RE.search
    i_touch = _INT_COLS.index(HEADER.index("touch"))
    for lineno, cells in data_rows(reader, name, len(HEADER), 0, MAX_LOG_ROWS, ProbeLogError,
                                   _ROWS_WHAT):
        strs = [cells[i].strip() for i in _STR_COLS]
        try:
            if not (all(int_m(cells[i]) for i in _INT_COLS)
                    and all(float_m(cells[i]) for i in _FLOAT_COLS)
                    and strs[0] and all(len(s) <= MAX_ID_CHARS and not ctrl(s) for s in strs)):
                raise ValueError
            ints = [int(cells[i]) for i in _INT_COLS]
            floats = [float(cells[i]) for i in _FLOAT_COLS]
            if not all(lo <= v <= hi for v, (lo, hi) in zip(floats, _FLOAT_RANGES,
                                                            strict=True)):
                raise ValueError
        except ValueError:
            raise _bad_cell(name, lineno, cells) from None
        ball = strs[1]
        if ids is not None and ball not in ids:
            raise ProbeLogError(f"{name}: line {lineno}: column ball: unknown ball id "
                                f"{ball!r} (artefact {artefact.name} has {sorted(ids)})")
        if not 1 <= ints[i_touch] <= TOUCHES_PER_BALL:
            raise ProbeLogError(f"{name}: line {lineno}: column touch: {ints[i_touch]} outside "
                                f"1..{TOUCHES_PER_BALL}")
        log._append(strs, ints, floats, lineno, lookup)
    return log


def _fmt(v: object) -> str:
    return repr(float(v)) if isinstance(v, float) else str(v)


def write_log(path: Path | str | io.TextIOBase, rows: Iterable[LogRow]) -> None:
    """Write rows in the contract format (floats in shortest round-trip form)."""
    write_lines(path, [MAGIC, ",".join(HEADER),
                       *(",".join(_fmt(v) for v in astuple(r)) for r in rows)])


def write_lines(path: Path | str | io.TextIOBase, lines: Sequence[str]) -> None:
    """Write ``lines`` (each then a newline) to a UTF-8 file or a text stream."""
    text = "\n".join(lines) + "\n"
    _ = path.write(text) if isinstance(path, io.TextIOBase) else Path(path).write_text(
        text, encoding="utf-8")
