"""LinuxCNC: the kins pins' new values as halcmd lines (live) and patched into the HAL file.

``render`` gives ``setp <pin> <value>`` lines for ``halcmd -f`` (the trt kins read their pins
at every call: the change is live at once); ``patch_hal_file`` rewrites the matching ``setp``
lines of the machine's HAL file (config/linuxcnc/rumba_xyzbc.hal), which is what survives a
restart — both are needed, the first without the second is lost at the next start.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from typing import TYPE_CHECKING

from contracts.controller_kinematics import ControllerKinematics
from programs.compensation.common import (
    CompensationError,
    CompensationOutput,
    Value,
    comment,
    degrees,
    describe,
    filename,
    fmt_value,
    listing,
    title,
    values,
)

if TYPE_CHECKING:
    from identification.compensation import ParamChange

_SETP = re.compile(r"\A([ \t]*setp[ \t]+)(\S+)([ \t]+)(\S+)")
MATCH_MM = 1e-6
"""The HAL file's value must equal the section's old value within this (mm)."""


def render(spec: ControllerKinematics, changes: Sequence[ParamChange], *, run_id: str,
           machine: str, rollback: bool = False) -> CompensationOutput:
    """halcmd lines setting the new pin values (``rollback``: the old ones back); an orientation
    pin (xyzbc_head_kins) holds the link in degrees."""
    vals = values(spec, changes, orientation=degrees, rollback=rollback)
    lines = [f"# {comment(title(run_id, machine, rollback))}",
             "# apply live: halcmd -f this file; keep after a restart: patch the HAL file"]
    for r in listing(vals):  # the strings the person confirmed
        lines.append(f"# {comment(describe(r))}")
        lines.append(f"setp {r.address} {r.written}")
    return CompensationOutput("\n".join(lines) + "\n", filename(run_id, machine, "hal", rollback),
                              vals)


def patch_hal_file(text: str, vals: Sequence[Value]) -> str:
    """``text`` (a HAL file) with the value of each ``setp <address>`` line replaced by the new
    one; every other byte kept. Refused: a pin whose ``setp`` line is missing or appears twice,
    or whose value in the file is not the old value (a stale machine file)."""
    lines = text.splitlines(keepends=True)
    for v in vals:
        hits = [i for i, line in enumerate(lines)
                if (m := _SETP.match(line)) and m.group(2) == v.address]
        if not hits:
            raise CompensationError(f"HAL file: no 'setp {v.address}' line to change")
        if len(hits) > 1:
            raise CompensationError(f"HAL file: 'setp {v.address}' appears {len(hits)} times "
                                    f"(lines {', '.join(str(i + 1) for i in hits)})")
        i = hits[0]
        m = _SETP.match(lines[i])
        assert m is not None
        try:
            current = float(m.group(4))
        except ValueError:
            raise CompensationError(f"HAL file line {i + 1}: {v.address} value "
                                    f"{m.group(4)!r} is not a number") from None
        if abs(current - v.old) > MATCH_MM:
            raise CompensationError(
                f"HAL file line {i + 1}: {v.address} is {m.group(4)}, expected the old value "
                f"{fmt_value(v.old, v.unit)}: the machine file's controller_kinematics is stale")
        lines[i] = m.group(1) + m.group(2) + m.group(3) + fmt_value(v.new, v.unit) + \
            lines[i][m.end():]
    return "".join(lines)


__all__ = ["MATCH_MM", "patch_hal_file", "render"]
