"""The centres CSV (README "Data contract: ball centres"): sphere centres measured by any
instrument, one row per (run, repeat, pose, ball) — read and validate, write.

Format: first line ``# rumba-centres v1``; then optional preamble lines, ``## free text`` (a
comment: provenance, instrument serial …) or ``# key: value`` with the keys of ``KEYS`` (an
unknown or repeated key is an error); then the header ``HEADER``, one row per centre.

* ``frame: machine`` (default): x/y/z are controller X Y Z, as the touch probe would read them
  with the stylus centre on the ball centre. ``frame: instrument``: a rigid motion (rotation +
  translation, unknown) of that frame — a CMM, a camera or a tracker reporting in its own axes;
  the analysis estimates the six frame parameters with the setup.
* ``b``/``c`` columns: the machine's two rotary axes in alphabetical order, as in the probing log;
  ``*_cmd_deg`` commanded (one value per pose), ``b_deg``/``c_deg`` as read back (an instrument
  that does not read the controller repeats the commanded value).
* ``u_um``: the standard uncertainty of the centre (µm, each coordinate); empty when not stated,
  stated on every row or on none. ``repeatability_um`` (one or three numbers, x y z) states it
  for the whole file instead.

Reading is as strict as the probing log's and shares its helpers (``contracts.probing_log``):
plain ASCII decimal numbers, the same ranges and ceilings (64 MiB, 4 096 bytes per line,
``MAX_CENTRE_ROWS`` rows = the touch ceiling / 5), every error one ``CentresFileError`` naming
file, line and column. A repeated (run, repeat, pose, ball) or (run, seq) is an error naming both
lines, as is one pose number with two commanded indexations; ``seq`` gaps are a warning.
"""

from __future__ import annotations

import csv
import io
import math
import warnings
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import astuple, dataclass, field, fields
from pathlib import Path

import numpy as np

from contracts.probing_log import (
    CONTROL_RE,
    COUNT_SYNTAX,
    FLOAT_RE,
    INT_RE,
    MAX_ID_CHARS,
    MAX_LOG_ROWS,
    NUMBER_SYNTAX,
    RANGES,
    TOUCHES_PER_BALL,
    PoseRow,
    ProbeLogError,
    ProbeLogWarning,
    byte_lines,
    data_rows,
    decoded,
    duplicate_key,
    seq_gaps,
    write_lines,
)
from identification.model import Artefact

MAGIC = "# rumba-centres v1"
HEADER = ["run_id", "seq", "t_s", "repeat", "pose", "b_cmd_deg", "c_cmd_deg", "b_deg", "c_deg",
          "ball", "x_mm", "y_mm", "z_mm", "u_um"]
FRAMES = ("machine", "instrument")
KEYS = ("frame", "instrument", "source", "repeatability_um")
MAX_CENTRE_ROWS = MAX_LOG_ROWS // TOUCHES_PER_BALL  # one centre per five touches
MAX_U_UM = 1e4  # a stated centre uncertainty beyond 1 cm is a unit mistake
_ROWS_WHAT = "centre rows (the reader's ceiling)"
_RANGES_C = {**{k: RANGES[k] for k in ("t_s", "b_cmd_deg", "c_cmd_deg", "b_deg", "c_deg",
                                        "x_mm", "y_mm", "z_mm")}, "u_um": (0.0, MAX_U_UM)}


class CentresFileError(ProbeLogError):
    """The centres file cannot be used as is; the message names file, line and column."""


@dataclass(frozen=True, slots=True)
class CentreRow(PoseRow):
    """One measured ball centre as in the CSV (columns in the same order); ``u_um`` NaN when
    the file does not state it."""

    b_deg: float
    c_deg: float
    ball: str
    x_mm: float
    y_mm: float
    z_mm: float
    u_um: float = math.nan


COLUMN_TYPES = {f.name: f.type for f in fields(CentreRow)}


@dataclass
class CentresFile:
    """A read centres file: its rows and the preamble keys."""

    name: str
    rows: list[CentreRow]
    frame: str = "machine"
    instrument: str = ""
    source: str = ""
    repeatability_um: tuple[float, float, float] | None = None
    comments: list[str] = field(default_factory=list)
    lines: list[int] = field(default_factory=list)  # the file line of each row

    @property
    def u_stated(self) -> bool:
        return bool(self.rows) and not math.isnan(self.rows[0].u_um)

    def column(self, name: str) -> np.ndarray:
        """One column as a numpy array (strings as an object array)."""
        kind = COLUMN_TYPES[name]
        dtype = object if kind == "str" else (np.int64 if kind == "int" else float)
        return np.array([getattr(r, name) for r in self.rows], dtype)


def _printable(text: str) -> bool:
    return len(text) <= MAX_ID_CHARS and not CONTROL_RE.search(text)


def parse_repeatability(text: str, where: str) -> tuple[float, float, float]:
    """``s`` or ``sx,sy,sz`` (µm, positive, ASCII decimal) → (sx, sy, sz)."""
    cells = text.split(",")
    if len(cells) not in (1, 3) or not all(FLOAT_RE.fullmatch(c) for c in cells):
        raise CentresFileError(f"{where}: expected one or three positive numbers (centre std "
                               f"x,y,z in µm), got {text.strip()[:40]!r}")
    v = [float(c) for c in cells]
    if not all(0.0 < x <= MAX_U_UM for x in v):
        raise CentresFileError(f"{where}: {text.strip()[:40]} outside (0, {MAX_U_UM:g}] µm")
    return (v[0], v[0], v[0]) if len(v) == 1 else (v[0], v[1], v[2])


def _key_line(cf: CentresFile, text: str, where: str, seen: set[str]) -> None:
    key, sep, value = text[1:].partition(":")
    key, value = key.strip(), value.strip()
    if not sep or key not in KEYS:
        raise CentresFileError(f"{where}: expected '# key: value' with a key among "
                               f"{', '.join(KEYS)} (or '## comment'), got {text.strip()[:60]!r}")
    if key in seen:
        raise CentresFileError(f"{where}: key {key!r} given twice")
    seen.add(key)
    if not _printable(value):
        raise CentresFileError(f"{where}: {key}: expected at most {MAX_ID_CHARS} printable "
                               "characters")
    if key == "frame":
        if value not in FRAMES:
            raise CentresFileError(f"{where}: frame: expected one of {', '.join(FRAMES)}, got "
                                   f"{value[:40]!r}")
        cf.frame = value
    elif key == "repeatability_um":
        cf.repeatability_um = parse_repeatability(value, f"{where}: repeatability_um")
    else:
        setattr(cf, key, value)


def _cell(name: str, lineno: int, col: str, cell: str) -> object:
    """One cell → its typed value, or a ``CentresFileError`` naming line and column."""
    kind = COLUMN_TYPES[col]
    if kind == "str":
        s = cell.strip()
        if not s or not _printable(s):
            raise CentresFileError(f"{name}: line {lineno}: column {col}: expected an id of 1 to "
                                   f"{MAX_ID_CHARS} printable characters, got {s[:40]!r}")
        return s
    if kind == "int":
        if not INT_RE.fullmatch(cell) or int(cell) < 0:
            raise CentresFileError(f"{name}: line {lineno}: column {col}: expected an integer "
                                   f"≥ 0, got {cell[:40]!r} ({COUNT_SYNTAX})")
        return int(cell)
    if col == "u_um" and not cell.strip():
        return math.nan
    lo, hi = _RANGES_C[col]
    if not FLOAT_RE.fullmatch(cell):
        raise CentresFileError(f"{name}: line {lineno}: column {col}: expected a finite number, "
                               f"got {cell[:40]!r} ({NUMBER_SYNTAX})")
    v = float(cell)
    if not lo <= v <= hi or (col == "u_um" and v <= 0.0):
        bound = f"(0, {hi:g}]" if col == "u_um" else f"[{lo:g}, {hi:g}]"
        raise CentresFileError(f"{name}: line {lineno}: column {col}: {cell.strip()} outside "
                               f"{bound}")
    return v


def read_centres(path: Path | str, artefact: Artefact | None = None,
                 text: str | None = None) -> CentresFile:
    """Read and validate a centres file (``text`` instead of the file content if given)."""
    with byte_lines(path, text, CentresFileError, noun="file",
                    rows=(MAX_CENTRE_ROWS, _ROWS_WHAT)) as raw:
        return _read(raw, str(path), artefact)


def _read(raw: Iterable[bytes], name: str, artefact: Artefact | None) -> CentresFile:
    lines = decoded(raw, name, CentresFileError, printable=True)
    cf = CentresFile(name, [])
    first = next(lines, "")
    if first.strip() != MAGIC:
        raise CentresFileError(f"{name}: line 1: expected {MAGIC!r} (not a rumba centres file?)")
    lineno, seen = 1, set()
    for text in lines:
        lineno += 1
        if not text.strip():
            continue
        if text.startswith("##"):
            comment = text[2:].strip()
            if CONTROL_RE.search(comment.replace("\t", " ")):
                raise CentresFileError(f"{name}: line {lineno}: a control character (NUL, "
                                       "escape …) in a comment: expected printable text")
            cf.comments.append(comment)
            continue
        if text.startswith("#"):
            _key_line(cf, text, f"{name}: line {lineno}", seen)
            continue
        if [h.strip() for h in text.rstrip("\r\n").split(",")] != HEADER:
            raise CentresFileError(f"{name}: line {lineno}: expected the header "
                                   f"{','.join(HEADER)}")
        break
    else:
        raise CentresFileError(f"{name}: no header line {','.join(HEADER)}")
    reader = csv.reader(lines)
    try:
        cf.rows, cf.lines = _rows(reader, name, lineno, artefact)
    except csv.Error as e:
        raise CentresFileError(f"{name}: line {lineno + reader.line_num}: not CSV: {e}") from None
    if not cf.rows:
        raise CentresFileError(f"{name}: no centre rows after the header")
    check_rows(cf, name)
    return cf


def _rows(reader: Iterator[list[str]], name: str, offset: int,
          artefact: Artefact | None) -> tuple[list[CentreRow], list[int]]:
    ids = set(artefact.ids) if artefact is not None else None
    rows: list[CentreRow] = []
    where: list[int] = []
    for lineno, cells in data_rows(reader, name, len(HEADER), offset, MAX_CENTRE_ROWS,
                                   CentresFileError, _ROWS_WHAT):
        row = CentreRow(*(_cell(name, lineno, col, c) for col, c in zip(HEADER, cells,
                                                                         strict=True)))
        if ids is not None and row.ball not in ids:
            raise CentresFileError(f"{name}: line {lineno}: column ball: unknown ball id "
                                   f"{row.ball!r} (artefact {artefact.name} has {sorted(ids)})")
        if rows and math.isnan(row.u_um) != math.isnan(rows[0].u_um):
            raise CentresFileError(f"{name}: line {lineno}: column u_um: "
                                   f"{'empty' if math.isnan(row.u_um) else 'stated'}, but "
                                   f"{'stated' if math.isnan(row.u_um) else 'empty'} on the "
                                   "first row (state it on every row or on none)")
        rows.append(row)
        where.append(lineno)
    return rows, where


def check_rows(cf: CentresFile, name: str) -> None:
    """Duplicates are errors, one pose with two commanded indexations too; seq gaps warn
    (``cf.lines``: the file line of each row, for the messages)."""
    rows, file_line = cf.rows, cf.lines
    lines = np.arange(len(rows))  # row indices (file order); messages name file lines
    run_codes = {r: i for i, r in enumerate(dict.fromkeys(r.run_id for r in rows))}
    ball_codes = {b: i for i, b in enumerate(dict.fromkeys(r.ball for r in rows))}
    run = np.array([run_codes[r.run_id] for r in rows], np.int64)
    ball = np.array([ball_codes[r.ball] for r in rows], np.int64)
    col = {c: cf.column(c) for c in ("seq", "repeat", "pose")}
    dup = duplicate_key(np.stack([run, col["repeat"], col["pose"], ball], 1), lines)
    if dup is not None:
        r = rows[dup[1]]
        raise CentresFileError(f"{name}: line {file_line[dup[1]]}: ball {r.ball} pose {r.pose} "
                               f"repeat {r.repeat} run {r.run_id} duplicates line "
                               f"{file_line[dup[0]]}")
    dup = duplicate_key(np.stack([run, col["seq"]], 1), lines)
    if dup is not None:
        r = rows[dup[1]]
        raise CentresFileError(f"{name}: line {file_line[dup[1]]}: seq {r.seq} of run "
                               f"{r.run_id} duplicates line {file_line[dup[0]]}")
    cmd: dict[tuple[str, int], int] = {}
    for k, r in enumerate(rows):
        j = cmd.setdefault((r.run_id, r.pose), k)
        if (rows[j].b_cmd_deg, rows[j].c_cmd_deg) != (r.b_cmd_deg, r.c_cmd_deg):
            raise CentresFileError(f"{name}: line {file_line[k]}: pose {r.pose} commanded at "
                                   f"b={r.b_cmd_deg:g}, c={r.c_cmd_deg:g} but at "
                                   f"b={rows[j].b_cmd_deg:g}, c={rows[j].c_cmd_deg:g} on line "
                                   f"{file_line[j]} (a pose number is one indexation)")
    for code, run_id in enumerate(run_codes):
        shown = seq_gaps(col["seq"][run == code])
        if shown:
            warnings.warn(f"{name}: run {run_id}: seq {shown} missing (centres lost or rows "
                          "deleted)", ProbeLogWarning, stacklevel=4)


def _fmt(v: object) -> str:
    if isinstance(v, float):
        return "" if math.isnan(v) else repr(v)
    return str(v)


def write_centres(path: Path | str | io.TextIOBase, rows: Iterable[CentreRow], *,
                  frame: str = "machine", instrument: str = "", source: str = "",
                  repeatability_um: Sequence[float] | None = None,
                  comments: Sequence[str] = ()) -> None:
    """Write rows in the contract format (floats in shortest round-trip form)."""
    if frame not in FRAMES:
        raise ValueError(f"frame must be one of {FRAMES}, got {frame!r}")
    out = [MAGIC, *(f"## {c}" for c in comments), f"# frame: {frame}"]
    if instrument:
        out.append(f"# instrument: {instrument}")
    if source:
        out.append(f"# source: {source}")
    if repeatability_um is not None:
        out.append("# repeatability_um: " + ",".join(repr(float(x)) for x in repeatability_um))
    out.append(",".join(HEADER))
    write_lines(path, out + [",".join(_fmt(v) for v in astuple(r)) for r in rows])
