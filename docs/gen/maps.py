"""The address maps a controller's side must implement: the OPC UA nodes, the Modbus registers,
the serial DNC lines and the CAN panel frames, from the tables the links and the simulator use
(``contracts.opcua_space``, ``contracts.modbus_map``, ``contracts.result_lines``,
``contracts.can_frames``)."""

from __future__ import annotations

from docs.gen.text import cell, code, header, table


def opcua() -> str:
    from contracts import opcua_space as s

    rows = [[code(n.role), code(n.path), n.kind, n.writer, cell(n.doc)] for n in s.NODES]
    return "\n".join([
        header("OPC UA address map", "contracts/opcua_space.py"),
        "The **gateway profile**: what a PLC's or an edge box's OPC UA server implements for "
        "`transport: opcua` (the daemon is the client); no control ships it — a SINUMERIK as "
        "delivered is `transport: sinumerik`, its own server. String node ids in the namespace "
        f"{code(s.NAMESPACE_URI)}, SINUMERIK-style: the handshake and the touch counter are R "
        "parameters of channel 1 (Double, as on an 840D), the results channel GUD arrays, "
        "program handling a method set. Every id can be replaced per machine in the link's "
        "configuration: `nodes: {role: \"ns=…;s=…\"}`.\n",
        table(["role", "node id (`ns=<index>;s=…`)", "type", "written by", "meaning"], rows),
        f"The result arrays are a ring of {s.RING_SLOTS} slots: the daemon reads every slot "
        "between the last counter it saw and the current one, so up to "
        f"{s.RING_SLOTS} touches may arrive between two notifications without loss. The "
        f"state node takes the values {', '.join(code(x) for x in s.STATES)}.\n",
        "## Results server: the last map of the linear axes\n",
        "Not the gateway profile: what the daemon's own OPC UA results server (`opcua_server` "
        "in daemon.yaml) serves per machine, beside its `Check` object and its OPC 40001-101 "
        "`ResultManagement`: the object `<machine>.Map` in the namespace "
        f"{code(s.RESULTS_NAMESPACE_URI)} holds the figures of the machine's last journaled "
        "map (`rumba map --store`, or the daemon's map job). Each µm variable carries an "
        "`EngineeringUnits` property (EUInformation, UNECE `4H`, µm) and is NaN when the "
        "machine has no map or the map not that figure. The server shows a new map at its "
        "start, at a run's end and within 10 s of its journaling.\n",
        table(["variable (`ns=<index>;s=<machine>.Map.…`)", "type", "unit", "meaning"],
              [[code(v.name), v.kind, "µm" if v.unit == "um" else "", cell(v.doc)]
               for v in s.MAP_VARIABLES]),
    ])


def modbus() -> str:
    from contracts import modbus_map as m

    regs = [[code(r.name), str(r.address), str(r.words), r.type, r.writer, cell(r.doc)]
            for r in m.REGISTERS]
    slot = [[code(name), f"+{offset}", kind, cell(doc)] for name, offset, kind, doc
            in m.SLOT_LAYOUT]
    return "\n".join([
        header("Modbus TCP register map", "contracts/modbus_map.py"),
        "The **gateway profile**: what the control's PLC or a gateway beside it serves for "
        "`transport: modbus` (the daemon is the client); rumba's own map, which no control "
        f"ships. Map id {m.MAP_ID:#06x}, version {m.MAP_VERSION}. All data are holding "
        "registers (function codes 3 read, 6/16 write), protocol addresses 0-based (Modicon "
        "reference = address + 40001) relative to the link's `base_address`. Byte order "
        "big-endian inside a register; 32-bit values high word first (ABCD). Positions are "
        f"int32 fixed point: linear axes in 1/{m.LINEAR_COUNTS_PER_MM} mm (0.1 µm), rotary "
        f"axes in 1/{m.ROTARY_COUNTS_PER_DEG} degree (µdeg).\n",
        table(["register", "address", "words", "type", "written by", "meaning"], regs),
        f"## A result slot\n\n{m.RING_SLOTS} slots of {m.SLOT_WORDS} registers; slot *k* "
        f"starts at {m.BY_NAME['RESULT_RING'].address} + {m.SLOT_WORDS}·*k*.\n",
        table(["field", "offset", "type", "meaning"], slot),
        "## Codes\n",
        table(["register", "value", "meaning"],
              [[code("STATE"), str(v), code(k)] for k, v in m.STATE_CODES.items()]
              + [[code("COMMAND"), str(v), code(k)] for k, v in m.COMMANDS.items()]
              + [[code("ALARM_CODE"), str(k), v] for k, v in m.ALARM_CODES.items()]),
        f"The mailbox carries the program to the controller block by block: at most "
        f"{2 * m.MBX_DATA_WORDS} ASCII characters per block in `MBX_DATA`, its length in "
        "`MBX_LEN`, then `MBX_SEQ`, then `MBX_READY` = 1 last; the controller sets "
        "`MBX_READY` = 0 and `MBX_ACK` = the block number once it has taken the block.\n",
    ])


def serial() -> str:
    from contracts import result_lines as r
    from drivers.serial import lines

    fields = " ".join(r.RESULT_FIELDS)
    described = ("seq", "rep", "pose", "ball", "touch", "trig", "x", "y", "z", "r1", "r2")
    if tuple(r.RESULT_FIELDS) != described:
        raise SystemExit(f"docs/gen/maps.py: describe the result line's fields {r.RESULT_FIELDS}")
    verdict = [[code(d), code(v)] for d, v in r.VERDICT_VARIABLES.items()]
    return "\n".join([
        header("Serial DNC lines", "contracts/result_lines.py and drivers/serial/lines.py"),
        "What travels on the RS-232 line for `transport: serial` (and what the LinuxCNC "
        "program logs): the daemon sends the program as a tape (`%` … `%`, XON/XOFF "
        "honoured); the control prints one result line per touch, and its start-of-shift macro "
        "prints a request line.\n",
        "## Result line\n",
        f"```text\nRUMBA {fields.replace('rep', 'repeat', 1)}\n```\n",
        table(["field", "meaning"], [
            [code("seq"), "touch sequence number in the program (1-based)"],
            [code("repeat"), "repeat of the pose"],
            [code("pose"), "pose number"],
            [code("ball"), "ball id, 1-32 of `A-Za-z0-9_.-`"],
            [code("touch"), "1-5 (4 equator diagonals, the pole)"],
            [code("trig"), "1 the probe triggered, 0 the move ended without contact (the run "
                           "stops)"],
            [code("x y z"), f"latched position, mm, at most {r.MAX_RESULT_MM:g} in magnitude"],
            [code("r1 r2"), f"the two rotary axes (alphabetical), degrees, at most "
                            f"{r.MAX_RESULT_DEG:g} in magnitude"],
        ]),
        "Numbers as the control prints them (a sign and a leading or trailing point "
        "allowed). Any other line is not a result; a line starting with `RUMBA` that breaks "
        "this grammar stops the run with the line quoted. The program keeps the last "
        f"{r.RING_SLOTS} results in a ring of macro variables (touch *k* in slot "
        f"(*k* − 1) mod {r.RING_SLOTS}).\n",
        "## Start request and verdict\n",
        "The start-of-shift macro clears the verdict variable and prints\n",
        "```text\nRUMBA REQUEST <machine>\n```\n",
        "(the machine name: 1-32 of `A-Za-z0-9_.-`); requests repeated within "
        f"{lines.REQUEST_HOLDOFF_S:g} s of a run's end are echoes and are not served again. "
        "The daemon answers with a verdict program that writes the verdict code (1 PASS, "
        "2 WARN, 3 FAIL, 4 ERROR) where the macro reads it:\n",
        table(["dialect", "verdict variable"], verdict),
    ])


def can() -> str:
    from contracts import can_frames as c

    return "\n".join([
        header("CAN operator panel frames", "contracts/can_frames.py"),
        "Standard 11-bit identifiers from the panel's `base_id`.\n",
        table(["frame", "identifier", "bytes"], [
            ["button (panel → daemon)", f"base_id + {c.OFFSET_BUTTON}",
             "button code, counter"],
            ["lamp (daemon → panel)", f"base_id + {c.OFFSET_LAMP}",
             f"lamp code, progress % ({c.PROGRESS_UNKNOWN} = unknown), flags, alive counter"],
        ]),
        table(["button code", "button"], [[str(k), code(v)] for k, v in c.BUTTONS.items()]),
        table(["lamp code", "lamp"], [[str(v), code(k)] for k, v in c.LAMPS.items()]),
    ])
