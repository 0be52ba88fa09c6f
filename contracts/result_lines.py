"""What a probing program reports per touch: the result-line grammar, the ring of result slots
and the dialect names (gcode_templates/README.md) — one definition for programs, links and the
simulator."""

from __future__ import annotations

import math
import re

from contracts.dialects import DIALECTS
from contracts.messages import TOUCH_DIRECTIONS, ProbeHit

DIALECT_NAMES = tuple(DIALECTS)
"""Every controller dialect (``contracts.dialects.DIALECTS``), in this order wherever they are
listed."""

VERDICT_VARIABLES = {n: r.verdict_variable for n, r in DIALECTS.items()}
"""Where each dialect's verdict program writes the verdict code (1-4) and the start-of-shift
macro reads it (from the dialect records): Fanuc/Haas common variable #598 (retained, next to
the ring), Siemens R4 (the OPC UA map's verdict node /Channel/Parameter/R[u1,4]), Heidenhain
Q1598 (next to the ring counter Q1599), LinuxCNC user parameter #3998 (next to the ring)."""

RING_SLOTS = 8
"""Result slots on the controller, reused in turn (touch seq k lands in slot (k-1) % 8)."""

RESULT_COUNTERS = {n: r.result_counter for n, r in DIALECTS.items()}
"""The variable each dialect's program sets to the touch's seq after writing its slot."""

STOP_PROGRAMS = {n: r.stop_program for n, r in DIALECTS.items() if r.stop_program}
"""(program, variable) of a dialect whose link cannot write the controller's variables (LSV2
reads files and states, it writes no Q parameter): before each probing move the program calls
the small stop program the link writes next to it and ends (M30, no error) when it set the
variable to 1; the link writes it with 0 before the run and with 1 to stop it."""

HANDSHAKE_VARIABLES = {n: r.handshake_variables for n, r in DIALECTS.items()
                       if r.handshake_variables}
"""(ack, stop) of a program whose results a link reads from the controller's variables (the
SINUMERIK OPC UA server, the Haas data port): the link writes ack = the last touch counter it has
read, and the program waits before a probing move while counter - ack = ``RING_SLOTS`` (the slot
it would overwrite is unread); stop = 1 makes the program end at its next touch (M30 after a
message: no alarm to acknowledge). Next to the ring: Fanuc/Haas common variables #688/#689
(Haas NGC #10688/#10689, general purpose, kept at power off), Siemens R188/R189 (MD28050
MM_NUM_R_PARAM >= 190). The program never writes either: an ack or a stop written before the
cycle start holds."""
RESULT_FIELDS = ("seq", "rep", "pose", "ball", "touch", "trig", "x", "y", "z", "r1", "r2")
"""The fields of one result, in the order of a result line and of a slot's variables."""
SLOT_FIELDS = len(RESULT_FIELDS)

MAX_RESULT_MM = 1e5
"""Largest plausible latched linear position: no machine tool travels 100 m, so a larger value
is a garbled record, not a measurement (journaling it only moves the failure to analysis)."""
MAX_RESULT_DEG = 1e5
"""Largest plausible latched rotary position (a multi-turn axis stays far below)."""

_NUM = r"[+-]?(?:\d+\.?\d*|\.\d+)"
# re.ASCII: without it \d and \s also match '٣' or a no-break space, which no control prints
_LINE = re.compile(
    rf"^\s*RUMBA\s+(?P<seq>\d+)\s+(?P<rep>\d+)\s+(?P<pose>\d+)\s+(?P<ball>[A-Za-z0-9_.-]{{1,32}})"
    rf"\s+(?P<touch>[1-5])\s+(?P<trig>{_NUM})\s+(?P<x>{_NUM})\s+(?P<y>{_NUM})\s+(?P<z>{_NUM})"
    rf"\s+(?P<r1>{_NUM})\s+(?P<r2>{_NUM})\s*$", re.ASCII)


def parse_result_line(line: str) -> ProbeHit | None:
    """Decode one printed result line (DPRNT, WRITE, F-PRINT, LOG); None for any other output;
    ``ValueError`` naming what is wrong for a broken ``RUMBA`` line (a value is never guessed).

    The hit is unbound: rotary values under the log's column names ``b`` / ``c``, identity as
    printed (a ``TouchTable`` checks it against the program and fills the program's side)."""
    if not line.lstrip().startswith("RUMBA"):
        return None
    m = _LINE.fullmatch(line.rstrip("\r\n"))
    if not m:
        raise ValueError(f"result line does not match the grammar "
                         f"'RUMBA seq rep pose ball touch trig x y z r1 r2': {line.strip()!r}")
    g = m.groupdict()
    touch = int(g["touch"])
    r1, r2 = float(g["r1"]), float(g["r2"])
    trig = float(g["trig"])
    if trig not in (0.0, 1.0):
        raise ValueError(f"result line: trigger flag {g['trig']} is neither 0 nor 1: "
                         f"{line.strip()!r}")
    for key, limit, unit in (("x", MAX_RESULT_MM, "mm"), ("y", MAX_RESULT_MM, "mm"),
                             ("z", MAX_RESULT_MM, "mm"), ("r1", MAX_RESULT_DEG, "deg"),
                             ("r2", MAX_RESULT_DEG, "deg")):
        value = float(g[key])
        if not math.isfinite(value) or abs(value) > limit:
            raise ValueError(f"result line: {key} = {g[key][:24]} {unit} is beyond "
                             f"±{limit:g} {unit}: {line.strip()[:120]!r}")
    return ProbeHit(seq=int(g["seq"]), pose=int(g["pose"]), ball=g["ball"], touch=touch,
                    axes={"X": float(g["x"]), "Y": float(g["y"]), "Z": float(g["z"]),
                          "b": r1, "c": r2},
                    triggered=trig == 1.0, repeat=int(g["rep"]), raw=line.strip(),
                    b_cmd_deg=r1, c_cmd_deg=r2, direction=TOUCH_DIRECTIONS[touch])
