"""The probing-log CSV (DESIGN.md contract): read/validate, write, and turn touches into centres.

Format: first line ``# rumba-probing-log v1``, then the header ``HEADER``, one row per touch.
Reading is strict: a malformed row, a non-finite number, an unknown ball id, a touch outside
1..5 or a duplicated (run, repeat, pose, ball, touch) is a ``ProbeLogError`` naming file, line
and column — the data are ambiguous and nothing can be guessed. A ball-pose with fewer than
five touches (an aborted run) is dropped with a ``ProbeLogWarning``: the other groups are
complete and the estimator itself reports whether what is left is still enough.
"""

from __future__ import annotations

import csv
import io
import math
import warnings
from collections.abc import Iterable, Sequence
from dataclasses import astuple, dataclass, fields
from pathlib import Path

import numpy as np

from identification.model import Artefact, Centres
from identification.spherefit import fit_spheres

MAGIC = "# rumba-probing-log v1"
HEADER = ["run_id", "seq", "t_s", "repeat", "pose", "b_cmd_deg", "c_cmd_deg", "ball", "touch",
          "dir_x", "dir_y", "dir_z", "x_mm", "y_mm", "z_mm", "b_deg", "c_deg", "feed_mm_min"]
TOUCHES_PER_BALL = 5
ROTARY_SPREAD_DEG = 0.01  # latched B/C of the five touches of one group must agree this well


class ProbeLogError(ValueError):
    """The log cannot be used as is; the message names file, line and column."""


class ProbeLogWarning(UserWarning):
    """Something was left out of the analysis (e.g. an incomplete ball-pose)."""


@dataclass(frozen=True)
class LogRow:
    """One touch as in the CSV (columns in the same order)."""

    run_id: str
    seq: int
    t_s: float
    repeat: int
    pose: int
    b_cmd_deg: float
    c_cmd_deg: float
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


_TYPES = {f.name: f.type for f in fields(LogRow)}
_CONVERTERS = [{"str": str.strip, "int": int, "float": float}[_TYPES[h]] for h in HEADER]
_FLOAT_COLS = [i for i, h in enumerate(HEADER) if _TYPES[h] == "float"]


@dataclass(frozen=True)
class GroupHealth:
    """Sphere-fit health of one (run, repeat, pose, ball)."""

    run_id: str
    repeat: int
    pose: int
    ball: str
    radius_dev_um: float
    form_rms_um: float


@dataclass
class CentreData:
    """Centres fitted from a log, one per (run, repeat, pose, ball), in ``centres`` order."""

    centres: Centres
    repeat: np.ndarray
    health: list[GroupHealth]
    warnings: list[str]


def _parse(value: str, typ: str) -> int | float | str:
    if typ == "str":
        return value
    if typ == "int":
        return int(value)
    v = float(value)
    if not math.isfinite(v):
        raise ValueError("not a finite number")
    return v


def read_log(path: Path | str, artefact: Artefact | None = None,
             text: str | None = None) -> list[LogRow]:
    """Read and validate a probing log (``text`` instead of the file content if given)."""
    name = str(path)
    if text is None:
        try:
            text = Path(path).read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as e:
            raise ProbeLogError(f"{name}: cannot read: {e}") from None
    lines = text.splitlines()
    if not lines or lines[0].lstrip("\ufeff").strip() != MAGIC:
        raise ProbeLogError(f"{name}: line 1: expected {MAGIC!r} (not a rumba probing log?)")
    if len(lines) < 2 or [h.strip() for h in lines[1].split(",")] != HEADER:
        raise ProbeLogError(f"{name}: line 2: expected the header {','.join(HEADER)}")
    ids = set(artefact.ids) if artefact is not None else None
    rows: list[LogRow] = []
    seen: dict[tuple, int] = {}
    reader = csv.reader(io.StringIO("\n".join(lines[2:])))
    for lineno, cells in enumerate(reader, start=3):
        if not cells or (len(cells) == 1 and not cells[0].strip()):
            continue
        if len(cells) != len(HEADER):
            raise ProbeLogError(f"{name}: line {lineno}: expected {len(HEADER)} columns, "
                                f"got {len(cells)}")
        try:  # fast path; on any failure the slow path below names the column
            vals = [conv(cell) for conv, cell in zip(_CONVERTERS, cells, strict=True)]
            if not all(map(math.isfinite, (vals[i] for i in _FLOAT_COLS))):
                raise ValueError
        except ValueError:
            vals = []
            for col, cell in zip(HEADER, cells, strict=True):
                typ = _TYPES[col]
                try:
                    vals.append(_parse(cell.strip(), typ))
                except ValueError:
                    what = "an integer" if typ == "int" else "a finite number"
                    raise ProbeLogError(f"{name}: line {lineno}: column {col}: expected {what}, "
                                        f"got {cell!r}") from None
        row = LogRow(*vals)
        if not row.run_id:
            raise ProbeLogError(f"{name}: line {lineno}: column run_id: empty")
        if ids is not None and row.ball not in ids:
            raise ProbeLogError(f"{name}: line {lineno}: column ball: unknown ball id "
                                f"{row.ball!r} (artefact {artefact.name} has {sorted(ids)})")
        if not 1 <= row.touch <= TOUCHES_PER_BALL:
            raise ProbeLogError(f"{name}: line {lineno}: column touch: {row.touch} outside "
                                f"1..{TOUCHES_PER_BALL}")
        if row.pose < 0 or row.repeat < 0:
            raise ProbeLogError(f"{name}: line {lineno}: column pose/repeat: must be ≥ 0")
        key = (row.run_id, row.repeat, row.pose, row.ball, row.touch)
        if key in seen:
            raise ProbeLogError(f"{name}: line {lineno}: touch {row.touch} of ball {row.ball} "
                                f"pose {row.pose} repeat {row.repeat} run {row.run_id} "
                                f"duplicates line {seen[key]}")
        seen[key] = lineno
        rows.append(row)
    if not rows:
        raise ProbeLogError(f"{name}: no touch rows after the header")
    return rows


def _fmt(v: object) -> str:
    return repr(float(v)) if isinstance(v, float) else str(v)


def write_log(path: Path | str | io.TextIOBase, rows: Iterable[LogRow]) -> None:
    """Write rows in the contract format (floats in shortest round-trip form)."""
    out = [MAGIC, ",".join(HEADER)]
    for r in rows:
        out.append(",".join(_fmt(v) for v in astuple(r)))
    text = "\n".join(out) + "\n"
    if isinstance(path, io.TextIOBase):
        path.write(text)
    else:
        Path(path).write_text(text, encoding="utf-8")


def rows_to_centres(rows: Sequence[LogRow], artefact: Artefact, stylus_radius_mm: float,
                    fixed_radius: bool = False, source: str = "log") -> CentreData:
    """Fit one centre per (run, repeat, pose, ball); incomplete groups are dropped with a
    ``ProbeLogWarning``. Several runs in one log are an error (setups differ between runs)."""
    runs = sorted({r.run_id for r in rows})
    if len(runs) > 1:
        raise ProbeLogError(f"{source}: contains runs {runs}; analyse one run at a time")
    groups: dict[tuple[int, int, str], list[LogRow]] = {}
    for r in rows:
        groups.setdefault((r.repeat, r.pose, r.ball), []).append(r)
    order = {b: i for i, b in enumerate(artefact.ids)}
    complete, msgs = [], []
    for key in sorted(groups, key=lambda k: (k[0], k[1], order.get(k[2], 1 << 30))):
        g = sorted(groups[key], key=lambda r: r.touch)
        if len(g) < TOUCHES_PER_BALL:
            have = [r.touch for r in g]
            msgs.append(f"{source}: ball {key[2]} pose {key[1]} repeat {key[0]}: only touches "
                        f"{have} of 1..{TOUCHES_PER_BALL}; this ball-pose is left out")
            continue
        spread = max(max(r.b_deg for r in g) - min(r.b_deg for r in g),
                     max(r.c_deg for r in g) - min(r.c_deg for r in g))
        if spread > ROTARY_SPREAD_DEG:
            raise ProbeLogError(f"{source}: ball {key[2]} pose {key[1]} repeat {key[0]}: latched "
                                f"b/c differ by {spread:.4f}° between touches "
                                "(the rotary axes moved during probing)")
        complete.append((key, g))
    for m in msgs:
        warnings.warn(m, ProbeLogWarning, stacklevel=2)
    if not complete:
        raise ProbeLogError(f"{source}: no ball-pose has all {TOUCHES_PER_BALL} touches")
    # (G, 5, 6) numbers per group: x y z b c t
    num = np.array([[(r.x_mm, r.y_mm, r.z_mm, r.b_deg, r.c_deg, r.t_s) for r in g]
                    for _, g in complete])
    r_nom = np.array([artefact.balls[order[k[2]]].diameter_mm / 2 + stylus_radius_mm
                      for k, _ in complete])
    fit = fit_spheres(num[:, :, :3], r_nom, fixed_radius=fixed_radius)
    pose = np.array([k[1] for k, _ in complete])
    ball = np.array([order[k[2]] for k, _ in complete])
    b_deg, c_deg, t_s = num[:, :, 3:].mean(axis=1).T
    health = [GroupHealth(runs[0], k[0], k[1], k[2], float(fit.radius_dev_um[i]),
                          float(fit.form_rms_um[i])) for i, (k, _) in enumerate(complete)]
    centres = Centres(pose, ball, b_deg, c_deg, fit.centre_mm, t_s)
    return CentreData(centres, np.array([k[0] for k, _ in complete]), health, msgs)
