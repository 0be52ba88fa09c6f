"""What the probing-log and centres reader tests share: the thesis artefact, valid centre rows,
and the line and byte mutations the fuzz tests apply to a valid file."""

from __future__ import annotations

import math
from pathlib import Path

from contracts.centres_file import CentreRow
from contracts.setup_files import load_artefact

CONFIG = Path(__file__).resolve().parents[2] / "config"
ARTEFACT = load_artefact(CONFIG / "artefacts/thesis_4ball.yaml")


def centre_rows(u: float = math.nan) -> list[CentreRow]:
    """Eight valid centres: every ball of ``ARTEFACT`` at two poses, ``u_um`` = ``u``."""
    out, seq = [], 0
    for pose, (b, c) in enumerate([(0.0, 0.0), (30.0, 90.0)]):
        for k, ball in enumerate(ARTEFACT.ids):
            seq += 1
            out.append(CentreRow("run-1", seq, 10.0 * seq, 0, pose, b, c, b + 1e-4, c, ball,
                                 -100.0 + k, 50.5 - pose, 152.125, u))
    return out


def mutate_line(lines: list[bytes], op: tuple) -> None:
    """Apply one line mutation to the non-empty ``lines`` in place: ``("drop", k)``,
    ``("dup", k)``, ``("swap", k, j)``, ``("bytes", k, pos, inserted)``, ``("long", k, n)``
    (n nines appended) or ``("bom", _)``; line and position indices wrap around."""
    kind, k = op[0], op[1] % len(lines)
    if kind == "drop":
        del lines[k]
    elif kind == "dup":
        lines.insert(k, lines[k])
    elif kind == "swap":
        j = op[2] % len(lines)
        lines[k], lines[j] = lines[j], lines[k]
    elif kind == "bytes":
        pos = op[2] % (len(lines[k]) + 1)
        lines[k] = lines[k][:pos] + op[3] + lines[k][pos:]
    elif kind == "long":
        lines[k] = lines[k] + b"9" * op[2]
    elif kind == "bom":
        lines[0] = b"\xef\xbb\xbf" + lines[0]


def mutate_whole(data: bytes, ops: list[tuple]) -> bytes:
    """The whole-file mutations of ``ops``, in order: ``("crlf", _)``, ``("cr", _)`` line ends,
    ``("truncate", n)`` (n wraps around)."""
    for op in ops:
        if op[0] == "crlf":
            data = data.replace(b"\n", b"\r\n")
        elif op[0] == "cr":
            data = data.replace(b"\n", b"\r")
        elif op[0] == "truncate":
            data = data[:op[1] % (len(data) + 1)]
    return data
