"""What rumba uses of a SINUMERIK 840D sl / 828D / ONE OPC UA server (Access MyMachine / OPC UA),
shared by the daemon's client (drivers/sinumerik) and the simulator's front-end
(simulators/frontends/sinumerik.py), so the profile is defined once; drivers/README.md renders it.

Sources (drivers/README.md names what each was checked against): the file system is OPC UA Part 5
Annex C / Part 20 (FileType, FileDirectoryType) under the server's "Part Programs" folder; R
parameters are ``/Channel/Parameter/R[u<channel>,<n>]`` Doubles; NC-global user GUDs
``/NC/_N_NC_GD3_ACX/<NAME>``; the program is selected with the server's ``Select`` method
under "Methods"; the server offers no NC start. Every node id can be overridden per machine
(``nodes:``); the results ring is the Siemens dialect's (R99 counter, R100-R187 slots) with the
handshake R188 (ack) / R189 (stop) of ``contracts.result_lines.HANDSHAKE_VARIABLES``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Literal

NAMESPACE_URI = "SinumerikVarProvider"
"""The namespace of the NC variables (index 2 on the controls seen in Siemens' examples)."""
ROOT = "Sinumerik"  # the object under Objects holding the NC's address space
FILE_SYSTEM = ("Sinumerik", "FileSystem")
PROGRAM_FOLDERS = ("Part Programs", "Sub Programs", "Work Pieces")
"""The FileDirectoryType folders the manual names; programs go to the first (.mpf files)."""
METHODS = ("Sinumerik", "Methods")
SELECT = "Select"
R_PATH = "/Channel/Parameter/R[u{channel},{n}]"
GUD_PATH = "/NC/_N_NC_GD3_ACX/{name}"
R_COUNT = 200
"""R parameters the simulated control holds (MD28050 MM_NUM_R_PARAM; rumba needs R0-R189)."""
PROGRAM_NAME = re.compile(r"^[A-Z][A-Z0-9_]{0,23}$")
"""A part-program name rumba writes (the file is <NAME>.MPF): 840D program names are letters,
digits and '_', starting with a letter; 24 characters keep the NC path within its limit."""

# OPC UA Part 5 FileType Open modes (Annex C.2.1): bit 0 read, 1 write, 2 erase existing, 3 append
OPEN_READ, OPEN_WRITE, OPEN_ERASE, OPEN_APPEND = 1, 2, 4, 8

PROG_STATUS = {1: "interrupted", 2: "stopped", 3: "running", 4: "waiting", 5: "aborted"}
"""``/Channel/State/progStatus`` (the program state of the NC/PLC interface: 1 interrupted,
2 stopped, 3 in progress, 4 waiting, 5 aborted — after RESET and after the program's end)."""
CHAN_STATUS = {0: "reset", 1: "interrupted", 2: "active"}
"""``/Channel/State/chanStatus``."""
ACTIVE_PROGRAM = (3, 4)  # running or waiting: a program occupies the channel
HELD_PROGRAM = (1, 2)  # interrupted (M0) or stopped (NC stop): still the selected program's run

Writer = Literal["cnc", "daemon"]


@dataclass(frozen=True)
class Role:
    role: str
    path: str  # default string identifier (``{channel}`` filled in)
    kind: Literal["Double", "UInt16", "String"]
    writer: Writer
    doc: str


ROLES: tuple[Role, ...] = (
    Role("request", R_PATH.format(channel="{channel}", n=1), "Double", "cnc",
         "start-of-shift request: the PLC (or the operator's start-of-shift program, which "
         "then ends) sets 1.0 and keeps it until DONE"),
    Role("busy", R_PATH.format(channel="{channel}", n=2), "Double", "daemon",
         "1.0 while the daemon runs the verification"),
    Role("done", R_PATH.format(channel="{channel}", n=3), "Double", "daemon",
         "1.0 when VERDICT is valid; cleared when REQUEST drops"),
    Role("verdict", R_PATH.format(channel="{channel}", n=4), "Double", "daemon",
         "0 none, 1 PASS, 2 WARN, 3 FAIL, 4 ERROR (R4: the Siemens dialect's verdict variable)"),
    Role("program_ready", R_PATH.format(channel="{channel}", n=5), "Double", "daemon",
         "1.0 while rumba's program is selected and waits for NC start (the PLC may start it "
         "then); 0 once it runs, is stopped or the run ends"),
    Role("prog_status", "/Channel/State/progStatus", "UInt16", "cnc",
         "program state: 1 interrupted, 2 stopped, 3 running, 4 waiting, 5 aborted"),
    Role("chan_status", "/Channel/State/chanStatus", "UInt16", "cnc",
         "channel state: 0 reset, 1 interrupted, 2 active"),
    Role("selected_program", "/Channel/ProgramInfo/selectedWorkPProg", "String", "cnc",
         "path of the program selected in the channel"),
)
BY_ROLE = {r.role: r for r in ROLES}
HANDSHAKE_ROLES = ("request", "busy", "done", "verdict", "program_ready")
"""Roles a shop maps onto its own R parameters or GUDs (``nodes:``)."""


def r_node(n: int, channel: int) -> str:
    """The string identifier of R parameter ``n`` of ``channel``."""
    return R_PATH.format(channel=channel, n=n)


def r_number(name: str) -> int:
    """``"R188"`` → 188 (a dialect's variable name); ValueError otherwise."""
    m = re.fullmatch(r"R(\d{1,4})", name)
    if not m:
        raise ValueError(f"{name!r} is not an R parameter")
    return int(m.group(1))


def role_path(role: str, channel: int) -> str:
    """The default string identifier of ``role`` for ``channel``."""
    return BY_ROLE[role].path.format(channel=channel)


def select_path(name: str) -> str:
    """The NC path the ``Select`` method is given for part program ``name`` (``_N_<NAME>_MPF``
    in the part-program directory: the NC's own file name of ``<NAME>.MPF``)."""
    return f"/_N_MPF_DIR/_N_{name}_MPF"


def file_name(name: str) -> str:
    """The file name in the "Part Programs" folder."""
    return f"{name}.MPF"
