"""Target 1: the probing-log reader (``contracts.probing_log.read_log``) on mutated shipped logs."""

from __future__ import annotations

import csv
import io
import math
import random
import re
import tempfile
from pathlib import Path

from benchmarks.fuzz.common import CONFIG, Tally, rand_cell, rand_text, run_case

EXAMPLE = CONFIG / "examples/thesis_annexB_14poses.csv"
ASCII_NUM = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?", re.ASCII)
LOCATED = re.compile(r"line \d+")
NUMERIC = {"seq", "t_s", "repeat", "pose", "b_cmd_deg", "c_cmd_deg", "touch", "dir_x", "dir_y",
           "dir_z", "x_mm", "y_mm", "z_mm", "b_deg", "c_deg", "feed_mm_min"}
COORDS = {"x_mm", "y_mm", "z_mm"}


def mutate_log(rng: random.Random, base: str) -> tuple[bytes, list[str]]:
    """A mutated log (bytes) and the list of operations applied (the reproducer)."""
    lines = base.splitlines()
    ops: list[str] = []
    for _ in range(rng.choice((1, 1, 1, 2, 3))):
        k = rng.randrange(2, len(lines))
        op = rng.choice(("cell", "cell", "cell", "cell", "dup", "drop", "seq", "line", "huge",
                         "cols", "header"))
        cells = lines[k].split(",")
        if op == "cell":
            c = rng.randrange(len(cells))
            cells[c] = rand_cell(rng)
            lines[k] = ",".join(cells)
            ops.append(f"line {k + 1} col {c} := {cells[c]!r}")
        elif op == "dup":
            lines.insert(k, lines[k])
            ops.append(f"duplicate line {k + 1}")
        elif op == "drop":
            del lines[k]
            ops.append(f"delete line {k + 1}")
        elif op == "seq":
            j = rng.randrange(2, len(lines))
            cells[1] = lines[j].split(",")[1] if lines[j].count(",") else "1"
            lines[k] = ",".join(cells)
            ops.append(f"line {k + 1} seq := {cells[1]!r} (copied from line {j + 1})")
        elif op == "line":
            lines[k] = rand_text(rng, 60)
            ops.append(f"line {k + 1} := {lines[k]!r}")
        elif op == "huge":
            cells[rng.randrange(len(cells))] = "7" * rng.choice((10_000, 1_000_000))
            lines[k] = ",".join(cells)
            ops.append(f"line {k + 1}: one cell of {len(lines[k])} characters")
        elif op == "cols":
            lines[k] = ",".join([*cells, rand_cell(rng)] if rng.random() < 0.5 else cells[:-1])
            ops.append(f"line {k + 1}: column count changed")
        else:
            lines[1] = lines[1].replace("x_mm", rng.choice(("X_mm", "x_mm ", "x_mm,x")))
            ops.append("header changed")
    eol = rng.choice(("\n", "\n", "\r\n", "\r"))
    text = eol.join(lines) + eol
    data = text.encode("utf-8")
    r = rng.random()
    if r < 0.08:
        data = b"\xef\xbb\xbf" + data
        ops.append("UTF-8 BOM")
    elif r < 0.16:
        at = rng.randrange(len(data))
        data = data[:at] + bytes([rng.choice((0xFF, 0xC3, 0x80, 0xFE))]) + data[at:]
        ops.append(f"non-UTF-8 byte at offset {at}")
    elif r < 0.22:
        at = rng.randrange(len(data))
        data = data[:at] + b"\x00" + data[at:]
        ops.append(f"NUL at offset {at}")
    if eol != "\n":
        ops.append(f"line ends {eol!r}")
    return data, ops


def violations(data: bytes) -> list[str]:
    """Reasons the reader must refuse this log (empty: acceptable)."""
    try:
        text = data.decode("utf-8").lstrip("\ufeff")
    except UnicodeDecodeError:
        return ["not UTF-8"]
    lines = text.splitlines()
    header = [h.strip() for h in lines[1].split(",")] if len(lines) > 1 else []
    why: list[str] = []
    seqs: set[tuple[str, str]] = set()
    for cells in csv.reader(io.StringIO("\n".join(lines[2:]))):
        if len(cells) != len(header):
            continue
        row = dict(zip(header, (c.strip() for c in cells), strict=True))
        for col in NUMERIC & set(row):
            v = row[col]
            if "_" in v:
                why.append(f"underscore number {col}={v!r}")
            elif not ASCII_NUM.fullmatch(v):
                why.append(f"not an ASCII number {col}={v!r}")
            elif not math.isfinite(float(v)):
                why.append(f"non-finite {col}={v!r}")
            elif col in COORDS and abs(float(v)) > 1e5:
                why.append(f"coordinate beyond 1e5 mm {col}={v!r}")
        key = (row.get("run_id", ""), row.get("seq", ""))
        if key in seqs:
            why.append(f"duplicate seq {key[1]} in run {key[0]!r}")
        seqs.add(key)
    return why


def fuzz(rng: random.Random, n: int, limit_s: float = 5.0) -> Tally:
    from contracts.probing_log import ProbeLogError, read_log
    from contracts.setup_files import load_artefact

    tally = Tally("probelog read_log")
    base = EXAMPLE.read_text(encoding="utf-8")
    artefact = load_artefact(CONFIG / "artefacts/thesis_4ball.yaml")
    with tempfile.TemporaryDirectory(prefix="rumba-fuzz-") as tmp:
        path = Path(tmp) / "log.csv"
        for i in range(n):
            data, ops = mutate_log(rng, base)

            def case(data: bytes = data) -> tuple[str, str]:
                path.write_bytes(data)
                try:
                    read_log(path, artefact)
                except ProbeLogError as e:
                    if not LOCATED.search(str(e)) and "cannot read" not in str(e):
                        tally.note("clean error without a line number")
                    return "clean", str(e)[:200]
                why = violations(data)
                return ("wrong", "; ".join(why)[:300]) if why else ("accepted", "")

            run_case(tally, limit_s, case, lambda i=i, ops=ops: f"case {i}: {'; '.join(ops)}")
    return tally
