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


# --------------------------------------------------------------- the daemon's results server
# Not the gateway profile above: what the daemon's own OPC UA results server (daemon/opcua/)
# serves to a quality system, per machine under Machinery's Machines folder, in the namespace
# below. ``MAP_VARIABLES`` are the children of ``<machine>.Map``: the last map of the linear
# axes journaled for that machine; a Double in µm carries an EngineeringUnits property
# (EUInformation, UNECE code 4H) and is NaN when the machine has no map or the figure none.
RESULTS_NAMESPACE_URI = "urn:rumba-cnc:results"


@dataclass(frozen=True)
class ResultVariable:
    name: str  # browse name; node id ``ns=<index>;s=<machine>.Map.<name>``
    kind: Literal["Double", "Int32", "UInt32", "String", "String[]", "DateTime"]
    unit: Literal["um", ""]
    doc: str


MAP_VARIABLES: tuple[ResultVariable, ...] = (
    ResultVariable("LastMapId", "String", "", "id of the last map result ('' : none): the map "
                   "job's run id, or map-… for one journaled by `rumba map --store`"),
    ResultVariable("LastMapTime", "DateTime", "", "when it was journaled (UTC)"),
    ResultVariable("LastMapVerdict", "String", "", "PASS, WARN or FAIL against the volumetric "
                   "limit; 'not judged' without a limit"),
    ResultVariable("LastMapEvaluation", "Int32", "", "its ResultEvaluationEnum as for a run: "
                   "0 Undefined, 1 OK, 2 NotOK, 3 NotDecidable"),
    ResultVariable("Limit", "String", "", "the limit it was judged against, as the report "
                   "words it"),
    ResultVariable("VolumetricMax_um", "Double", "um", "largest volumetric error over the "
                   "covered box (tool tip relative to the workpiece, rotary axes at zero, after "
                   "the best rigid-body motion)"),
    ResultVariable("VolumetricMaxU_um", "Double", "um", "standard uncertainty of "
                   "VolumetricMax_um"),
    ResultVariable("VolumetricRms_um", "Double", "um", "RMS of the volumetric error over the "
                   "covered box"),
    ResultVariable("PositioningMaxEXX_um", "Double", "um", "largest |EXX| over the covered X "
                   "stroke (NaN: not mapped)"),
    ResultVariable("PositioningMaxEYY_um", "Double", "um", "largest |EYY| over the covered Y "
                   "stroke"),
    ResultVariable("PositioningMaxEZZ_um", "Double", "um", "largest |EZZ| over the covered Z "
                   "stroke"),
    ResultVariable("Placements", "UInt32", "", "placements of the artefact the map was "
                   "fitted from"),
    ResultVariable("CoveredRange_mm", "String", "", "covered controller strokes, e.g. "
                   "'X -400..400, Y -300..300, Z -100..400'"),
    ResultVariable("NotObservable", "String[]", "", "directions and terms the data do not "
                   "determine (the map's observability statement)"),
)
