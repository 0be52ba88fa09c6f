"""Import sphere centres from a TwinCAT CNC / ISG kinematics-optimisation program: the calls
``L CYCLE [NAME = "SysCalibFitAddRecord.ecy" @P1 … @P6]`` of Beckhoff TF5245 "Sphere centre
points already calculated" (infosys.beckhoff.com/content/1033/tf5245_tc3_cnc_cycles_kinopt/
326272267.html): one call per measured pose, @P1-@P3 the centre X Y Z (mm), @P4-@P6 the
associated A, B, C (°; an axis the machine does not have is transferred as 0).

ISG NC syntax as documented there: ``;`` starts a comment to the end of the line, text in
``( … )`` is a comment, a ``\\`` at the end of a line continues the block on the next one. The
other statements (``#VAR`` blocks, the Init/Fit/End cycles) carry no centres and are skipped;
a record whose parameters are variables (``@P1 = V.L.RESULT_V[0]``, the "direct input"
variant that computes the centre on the control) cannot be imported and is an error naming the
line. The format has one sphere, no ball id and no times: every record is the ball the caller
names, ``t_s`` = 0, poses numbered in order of first appearance of an (A, B, C), a repeated
indexation counting as the next repeat.
"""

from __future__ import annotations

import re
from collections.abc import Iterator, Sequence
from pathlib import Path

from contracts.centres_file import MAX_CENTRE_ROWS, CentreRow, CentresFile
from contracts.importers.common import CentresImportError, continued, number, text_lines

RECORD_CYCLE = "SYSCALIBFITADDRECORD.ECY"
MAX_BLOCK_LINES = 64  # a record is 8 lines in the documentation
_CYCLE_RE = re.compile(r"\s*(?:N[0-9]+\s+)?L\s+CYCLE\s*\[(?P<body>.*)\]\s*",
                       re.IGNORECASE | re.DOTALL)
_NAME_RE = re.compile(r'NAME\s*=\s*"(?P<name>[^"]*)"', re.IGNORECASE)
_NC_SPECIAL = re.compile(r'[";(]')
_PARENS = re.compile(r"[()]")
_PARAM_RE = re.compile(r"@P(?P<k>[0-9]{1,3})\s*=\s*(?P<v>[^\s@]+)", re.IGNORECASE)


def _strip(line: str, where: str) -> str:
    """The line without its ``;`` and ``( … )`` comments (quotes protect both; nested
    parentheses counted). Scans from one special character to the next (a 64 MiB file of
    comments takes a second, not the several of a loop over every character)."""
    out, i = [], 0
    while (m := _NC_SPECIAL.search(line, i)) is not None:
        out.append(line[i:m.start()])
        i = m.end()
        if m.group() == ";":
            return "".join(out).rstrip()
        if m.group() == '"':  # kept whole; an unclosed quote runs to the end of the line
            end = line.find('"', i)
            i = len(line) if end < 0 else end + 1
            out.append(line[m.start():i])
            continue
        depth = 1
        while depth:
            p = _PARENS.search(line, i)
            if p is None:
                raise CentresImportError(f"{where}: a comment '(' is not closed on this line")
            depth += 1 if p.group() == "(" else -1
            i = p.end()
    out.append(line[i:])
    return "".join(out).rstrip()


def _blocks(path: Path | str, text: str | None) -> Iterator[tuple[int, str]]:
    """(first line number, block text) of every NC block, continuations joined."""
    name = str(path)
    bodies = ((n, _strip(line, f"{name}: line {n}")) for n, line in text_lines(path, text))
    return continued(bodies, name, "\\", "block", MAX_BLOCK_LINES, " ")


def read_kinopt(path: Path | str, ball: str, rotary: Sequence[str], *, text: str | None = None,
                run_id: str = "kinopt") -> CentresFile:
    """Centres of the SysCalibFitAddRecord calls of ``path``; ``ball``: the artefact's ball id
    the records measure; ``rotary``: the machine's two rotary axis letters (alphabetical),
    which become the ``b``/``c`` columns."""
    name = str(path)
    letters = [a.upper() for a in rotary]
    rows: list[CentreRow] = []
    lines: list[int] = []
    poses: dict[tuple[float, float], int] = {}
    visits: dict[int, int] = {}
    for n, block in _blocks(path, text):
        where = f"{name}: line {n}"
        m = _CYCLE_RE.fullmatch(block)
        if m is None:
            if RECORD_CYCLE in block.upper():
                raise CentresImportError(f"{where}: expected L CYCLE [NAME = "
                                         f"\"SysCalibFitAddRecord.ecy\" @P1 = … @P6 = …]")
            continue
        nm = _NAME_RE.search(m["body"])
        if nm is None or nm["name"].strip().upper() != RECORD_CYCLE:
            continue
        params: dict[int, str] = {}
        for p in _PARAM_RE.finditer(m["body"]):
            k, v = int(p["k"]), p["v"]
            if k in params:
                raise CentresImportError(f"{where}: @P{k} given twice")
            params[k] = v[:-1] if v.count("]") > v.count("[") else v  # "@P6 = 0]"
        missing = [f"@P{k}" for k in range(1, 7) if k not in params]
        if missing or set(params) - set(range(1, 7)):
            raise CentresImportError(f"{where}: SysCalibFitAddRecord needs @P1-@P6 (X Y Z of the "
                                     f"centre, A B C), got {sorted(f'@P{k}' for k in params)}")
        what = ["X", "Y", "Z", "A", "B", "C"]
        for k in range(1, 7):
            if params[k][:1].isalpha():
                raise CentresImportError(f"{where}: @P{k} = {params[k][:40]} is a variable: only "
                                         "centres already calculated (numbers) can be imported")
        v = [number(params[k + 1], where, f"@P{k + 1} ({what[k]})",
                    "x_mm" if k < 3 else "b_deg") for k in range(6)]
        angle = dict(zip("ABC", v[3:], strict=True))
        extra = [a for a in "ABC" if a not in letters and angle[a] != 0.0]
        if extra:
            raise CentresImportError(f"{where}: {extra[0]} = {angle[extra[0]]:g}, but the machine "
                                     f"has rotary axes {'/'.join(letters)} (an absent axis is "
                                     "transferred as 0)")
        b, c = angle[letters[0]], angle[letters[1]]
        pose = poses.setdefault((b, c), len(poses))
        rep = visits.get(pose, -1) + 1
        visits[pose] = rep
        if len(rows) >= MAX_CENTRE_ROWS:
            raise CentresImportError(f"{where}: more than {MAX_CENTRE_ROWS} records")
        rows.append(CentreRow(run_id, len(rows) + 1, 0.0, rep, pose, b, c, b, c, ball,
                              v[0], v[1], v[2]))
        lines.append(n)
    if not rows:
        raise CentresImportError(f"{name}: no L CYCLE [NAME = \"SysCalibFitAddRecord.ecy\" …] "
                                 "record with a centre (not a KinOpt centres program?)")
    return CentresFile(name, rows, frame="machine",
                       instrument="centres entered for TwinCAT KinOpt (SysCalibFitAddRecord)",
                       source=f"imported from {Path(name).name}", lines=lines)
