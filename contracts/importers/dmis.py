"""Import sphere centres from a DMIS results file (ANSI/DMIS 105.2, the CMM output ``.dmo``):
the actual-feature statements ``FA(label)=FEAT/SPHERE,[INNER|OUTER,]CART,x,y,z,diam``.

The statements read, as the DMIS standard writes them (the Dimensional Metrology Standards
Consortium's QIF → DMIS results example: ``FILNAM/…``, ``$$`` comments, ``UNITS/MM,ANGDEC``,
``FA(label)=FEAT/…``): ``$$`` starts a comment, a ``$`` at the end of a line continues the
statement, ``UNITS/MM`` or ``UNITS/INCH`` sets the length unit of the values that follow (mm
by default), ``DMISMN/'…'`` or ``FILNAM/'…'`` names the program. Every other statement
(nominals ``F(…)``, tolerances, motion, ``OUTPUT``) is skipped.

A CMM (or tracker, camera …) knows neither the machine's rotary axes nor which ball it sees:
the feature label says it, ``<ball>_P<pose>`` or ``<ball>_P<pose>_R<repeat>`` (e.g.
``F3_P7_R1``; DMIS labels are letters, digits and ``_``), ``<pose>`` indexing the poses of the
plan the machine ran (commanded = read: the instrument does not read the controller). Centres
are in the instrument's frame (``frame: instrument``); times are not part of the format (0).
"""

from __future__ import annotations

import re
from collections.abc import Iterator, Sequence
from pathlib import Path

from contracts.centres_file import MAX_CENTRE_ROWS, CentreRow, CentresFile
from contracts.importers.common import CentresImportError, continued, number, text_lines

MAX_STATEMENT_LINES = 64
MAX_LABEL_CHARS = 64
UNITS_MM = {"MM": 1.0, "INCH": 25.4}
_FA_RE = re.compile(r"FA\((?P<label>[^)]*)\)\s*=\s*FEAT/(?P<kind>[A-Z]+)(?P<rest>.*)", re.I)
_LABEL_RE = re.compile(r"(?P<ball>[A-Za-z0-9_]+?)_P(?P<pose>[0-9]{1,6})(?:_R(?P<rep>[0-9]{1,6}))?",
                       re.I)
_DMIS_TOKEN = re.compile(r"'[^']*(?:'|$)|\$\$|[^'$]+|\$")
_NAME_RE = re.compile(r"(?:DMISMN|FILNAM)\s*/\s*'(?P<name>[^']{0,200})'", re.I)


def _uncommented(line: str) -> str:
    """The line without its ``$$`` comment (a quote protects it; an unclosed quote runs to the
    end of the line), stripped; token by token, not character by character."""
    if "$$" not in line:
        return line.strip()
    body = []
    for tok in _DMIS_TOKEN.findall(line):
        if tok == "$$":
            break
        body.append(tok)
    return "".join(body).strip()


def _statements(path: Path | str, text: str | None) -> Iterator[tuple[int, str]]:
    """(first line number, statement) with ``$$`` comments removed and ``$`` continuations
    joined (a quote protects both)."""
    bodies = ((n, _uncommented(line)) for n, line in text_lines(path, text))
    for start, statement in continued(bodies, str(path), "$", "statement", MAX_STATEMENT_LINES):
        yield start, statement.strip()


def _sphere(rest: str, where: str, unit: float) -> tuple[float, float, float]:
    cells = [c.strip().upper() for c in rest.split(",")]
    if cells[:1] != [""]:
        raise CentresImportError(f"{where}: expected FEAT/SPHERE,[INNER|OUTER,]CART,x,y,z,diam")
    cells = cells[1:]
    if cells[:1] in (["INNER"], ["OUTER"]):
        cells = cells[1:]
    if cells[:1] != ["CART"] or len(cells) != 5:
        got = "polar coordinates (POL)" if cells[:1] == ["POL"] else f"{len(cells)} fields"
        raise CentresImportError(f"{where}: expected FEAT/SPHERE,[INNER|OUTER,]CART,x,y,z,diam "
                                 f"(Cartesian centre and diameter), got {got}")
    xyz = [number(c, where, f"sphere {a}", "x_mm") * unit
           for c, a in zip(cells[1:4], "xyz", strict=True)]
    diam = number(cells[4], where, "sphere diameter", "x_mm")
    if not diam > 0:
        raise CentresImportError(f"{where}: sphere diameter {cells[4]} is not positive")
    return xyz[0], xyz[1], xyz[2]


def read_dmis(path: Path | str, balls: Sequence[str], poses: Sequence[tuple[float, float]], *,
              text: str | None = None, run_id: str = "dmis") -> CentresFile:
    """Centres of the ``FA(…)=FEAT/SPHERE`` statements of ``path``; ``balls``: the artefact's
    ball ids; ``poses``: the (b, c) of each pose number of the plan (``<ball>_P<pose>``)."""
    name = str(path)
    ids = {b.upper(): b for b in balls}
    unit, program = 1.0, ""
    rows: list[CentreRow] = []
    lines: list[int] = []
    for n, st in _statements(path, text):
        where = f"{name}: line {n}"
        head = st.upper()
        if head.startswith("UNITS/"):
            u = head[6:].split(",")[0].strip()
            if u not in UNITS_MM:
                raise CentresImportError(f"{where}: expected UNITS/MM or UNITS/INCH, got "
                                         f"{st[:40]!r}")
            unit = UNITS_MM[u]
            continue
        nm = _NAME_RE.match(st)
        if nm is not None and not program:
            program = nm["name"]
            continue
        m = _FA_RE.match(st)
        if m is None or m["kind"].upper() != "SPHERE":
            continue
        label = m["label"].strip()
        lab = _LABEL_RE.fullmatch(label) if len(label) <= MAX_LABEL_CHARS else None
        if lab is None or lab["ball"].upper() not in ids:
            raise CentresImportError(f"{where}: feature label {m['label'][:40]!r}: expected "
                                     f"<ball>_P<pose>[_R<repeat>] with a ball among "
                                     f"{', '.join(balls)} (e.g. {balls[0]}_P0_R0)")
        pose, rep = int(lab["pose"]), int(lab["rep"] or 0)
        if pose >= len(poses):
            raise CentresImportError(f"{where}: feature {m['label']}: pose {pose}, but the plan "
                                     f"has poses 0..{len(poses) - 1}")
        if len(rows) >= MAX_CENTRE_ROWS:
            raise CentresImportError(f"{where}: more than {MAX_CENTRE_ROWS} sphere features")
        x, y, z = _sphere(m["rest"], where, unit)
        b, c = (float(v) for v in poses[pose])
        rows.append(CentreRow(run_id, len(rows) + 1, 0.0, rep, pose, b, c, b, c,
                              ids[lab["ball"].upper()], x, y, z))
        lines.append(n)
    if not rows:
        raise CentresImportError(f"{name}: no FA(label)=FEAT/SPHERE statement (not a DMIS results "
                                 "file with measured spheres?)")
    return CentresFile(name, rows, frame="instrument",
                       instrument="DMIS results" + (f" of {program}" if program else ""),
                       source=f"imported from {Path(name).name}", lines=lines)
