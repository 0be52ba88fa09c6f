"""The rumba OPC UA address space (node ids, types, who writes), shared by the daemon's client and
the simulator's server so the protocol is defined once; drivers/README.md renders it as a table.

Sinumerik-style string node ids: handshake flags and the touch counter are R parameters of
channel 1 (``/Channel/Parameter/R[u1,n]``, Double as on an 840D), results are channel GUD arrays
(``/NC/_N_CH_GUD_/RUMBA_*``), program handling is a method set under ``/Methods``. Every id can be
overridden per machine in the link config (``nodes: {role: "ns=…;s=…"}``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

NAMESPACE_URI = "urn:rumba-cnc:cnc"
RING_SLOTS = 32
"""Result ring length: the daemon reads every slot between the last seen and the current counter,
so up to 32 touches may arrive between two notifications without loss."""

Kind = Literal["Double", "Int32", "String", "Double[]", "Int32[]", "Method"]


@dataclass(frozen=True)
class NodeSpec:
    role: str
    path: str  # string identifier inside the namespace
    kind: Kind
    writer: Literal["cnc", "daemon", "-"]  # who writes it ("-" for methods)
    doc: str


NODES: tuple[NodeSpec, ...] = (
    NodeSpec("request", "/Channel/Parameter/R[u1,1]", "Double", "cnc",
             "start-of-shift request: the CNC sets 1.0 and keeps it until DONE"),
    NodeSpec("busy", "/Channel/Parameter/R[u1,2]", "Double", "daemon",
             "1.0 while the daemon runs the verification"),
    NodeSpec("done", "/Channel/Parameter/R[u1,3]", "Double", "daemon",
             "1.0 when VERDICT is valid; cleared when the CNC drops REQUEST"),
    NodeSpec("verdict", "/Channel/Parameter/R[u1,4]", "Double", "daemon",
             "0 none, 1 PASS, 2 WARN, 3 FAIL, 4 ERROR"),
    NodeSpec("touch_counter", "/Channel/Parameter/R[u1,5]", "Double", "cnc",
             "touches stored since the program was loaded; result n is in slot (n-1) mod 32"),
    NodeSpec("touch_ack", "/Channel/Parameter/R[u1,6]", "Double", "daemon",
             "last touch counter the daemon has read; the CNC waits while counter - ack = 32"),
    NodeSpec("state", "/Channel/State/rumbaState", "String", "cnc",
             "idle | running | hold | alarm | done"),
    NodeSpec("alarm", "/Channel/State/alarmText", "String", "cnc", "alarm text, '' if none"),
    NodeSpec("machine_time", "/Channel/State/machineTime", "Double", "cnc",
             "machine time of the current program, s"),
    NodeSpec("result_seq", "/NC/_N_CH_GUD_/RUMBA_SEQ", "Int32[]", "cnc",
             "touch sequence number per slot (the program's seq, 1-based)"),
    NodeSpec("result_x", "/NC/_N_CH_GUD_/RUMBA_X", "Double[]", "cnc", "latched X per slot, mm"),
    NodeSpec("result_y", "/NC/_N_CH_GUD_/RUMBA_Y", "Double[]", "cnc", "latched Y per slot, mm"),
    NodeSpec("result_z", "/NC/_N_CH_GUD_/RUMBA_Z", "Double[]", "cnc", "latched Z per slot, mm"),
    NodeSpec("result_b", "/NC/_N_CH_GUD_/RUMBA_B", "Double[]", "cnc",
             "first rotary axis (alphabetical) per slot, deg"),
    NodeSpec("result_c", "/NC/_N_CH_GUD_/RUMBA_C", "Double[]", "cnc",
             "second rotary axis per slot, deg"),
    NodeSpec("result_triggered", "/NC/_N_CH_GUD_/RUMBA_TRIG", "Int32[]", "cnc",
             "1 if the probe triggered, 0 if the move ended without contact"),
    NodeSpec("methods", "/Methods", "Method", "-", "object holding the methods below"),
    NodeSpec("load_program", "/Methods/LoadProgram", "Method", "-",
             "LoadProgram(text, dialect, files: String): store the program (files: JSON "
             "object name → text, e.g. FN 16 format files, or ''), reset counter and ring"),
    NodeSpec("start", "/Methods/Start", "Method", "-",
             "Start(): cycle start of the loaded program"),
    NodeSpec("abort", "/Methods/Abort", "Method", "-", "Abort(): reset, the program stops"),
)

BY_ROLE = {n.role: n for n in NODES}
RESULT_ROLES = ("result_seq", "result_x", "result_y", "result_z", "result_b", "result_c",
                "result_triggered")
STATES = ("idle", "running", "hold", "alarm", "done")


def node_id(role: str, ns: int, overrides: dict[str, str] | None = None) -> str:
    """The node id string of ``role`` (``ns=<ns>;s=<path>`` unless overridden)."""
    if overrides and role in overrides:
        return overrides[role]
    return f"ns={ns};s={BY_ROLE[role].path}"
