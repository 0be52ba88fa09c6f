"""The points CSV of ``rumba map --predict`` and the predictions it writes.

Input: lines starting with ``#`` are comments; the first other line is the header, exactly
``x_mm,y_mm,z_mm`` (commanded controller X Y Z, the rotary axes at zero); then one point per
row, plain ASCII decimal numbers (``nan``, ``inf``, ``1_0`` refused), |value| ≤ ``MAX_ABS_MM``,
at most ``MAX_POINTS`` rows, bounded like every input (``contracts.csv_lines``). Every refusal
is one ``MapPointsError`` naming file, line and column.

Output: header ``PREDICTION_HEADER``: the point, the volumetric error (µm, workpiece frame,
the map's rigid-body convention) and its standard uncertainty per component (µm).
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np

from contracts.csv_lines import CONTROL_RE, ProbeLogError, byte_lines, data_rows, decoded
from contracts.probing_log import FLOAT_RE

POINTS_HEADER = ["x_mm", "y_mm", "z_mm"]
PREDICTION_HEADER = ["x_mm", "y_mm", "z_mm", "ex_um", "ey_um", "ez_um", "ux_um", "uy_um",
                     "uz_um"]
MAX_POINTS = 1_000_000
MAX_ABS_MM = 1e5


class MapPointsError(ProbeLogError):
    """A points file that cannot be used; the message names file, line and column."""


def read_points(path: Path | str, text: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) commanded X Y Z (mm) of a points CSV (module docstring) and the file line of
    each point (N,), for messages about a point."""
    name = str(path)
    with byte_lines(path, text, MapPointsError, rows=(MAX_POINTS, "points"),
                    noun="points file") as raw:
        lines = decoded(raw, name, MapPointsError, printable=True)
        header_line = 0
        for n, line in enumerate(lines, start=1):
            if line.lstrip().startswith("#") or not line.strip():
                continue
            cells = [c.strip() for c in line.rstrip("\r\n").split(",")]
            if cells != POINTS_HEADER:
                shown = line.strip()[:80]
                raise MapPointsError(f"{name}: line {n}: expected the header "
                                     f"{','.join(POINTS_HEADER)}, got {shown!r}")
            header_line = n
            break
        if not header_line:
            raise MapPointsError(f"{name}: no header line {','.join(POINTS_HEADER)}")
        reader = csv.reader(_rest(lines))
        out, where = [], []
        for lineno, cells in data_rows(reader, name, 3, header_line, MAX_POINTS,
                                       MapPointsError, "points"):
            row = []
            for col, cell in zip(POINTS_HEADER, cells, strict=True):
                if CONTROL_RE.search(cell) or not FLOAT_RE.fullmatch(cell):
                    raise MapPointsError(f"{name}: line {lineno}: column {col}: expected a "
                                         f"decimal number, got {cell.strip()[:40]!r}")
                v = float(cell)
                if not abs(v) <= MAX_ABS_MM:
                    raise MapPointsError(f"{name}: line {lineno}: column {col}: {v:g} mm is "
                                         f"beyond ±{MAX_ABS_MM:g} mm")
                row.append(v)
            out.append(row)
            where.append(lineno)
    if not out:
        raise MapPointsError(f"{name}: no points after the header")
    return np.array(out, float), np.array(where, int)


def _rest(lines: object) -> object:
    for line in lines:  # type: ignore[attr-defined]
        if line.lstrip().startswith("#"):
            yield ""  # keeps csv's line count in step with the file's
        else:
            yield line


def write_predictions(path: Path | str | io.TextIOBase, xyz_mm: np.ndarray,
                      error_um: np.ndarray, u_um: np.ndarray) -> None:
    """The predictions CSV: points as given, error and u in µm to 0.1 nm."""
    lines = [",".join(PREDICTION_HEADER)]
    for p, e, u in zip(xyz_mm, error_um, u_um, strict=True):
        lines.append(",".join([*(repr(float(x)) for x in p), *(f"{x:.4f}" for x in e),
                               *(f"{x:.4f}" for x in u)]))
    text = "\n".join(lines) + "\n"
    if isinstance(path, io.TextIOBase):
        path.write(text)
    else:
        Path(path).write_text(text, encoding="utf-8")
