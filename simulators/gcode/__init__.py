"""G-code executor of the simulated controller: one interpreter core, one module per dialect."""

from __future__ import annotations

from typing import Any

from contracts.result_lines import DIALECT_NAMES
from simulators.gcode.core import Alarm, BlockQueue, MachineIO, ProbeOutcome, run
from simulators.gcode.fanuc import FanucInterpreter
from simulators.gcode.heidenhain import HeidenhainInterpreter
from simulators.gcode.linuxcnc import LinuxcncInterpreter
from simulators.gcode.siemens import SiemensInterpreter

DIALECTS = DIALECT_NAMES


class HaasInterpreter(FanucInterpreter):
    """Haas NGC: Fanuc macro syntax; skip positions by letter (#5064 A, #5065 B, #5066 C)."""

    def store_probe(self, latched: dict[str, float], triggered: bool) -> None:
        for a, v in latched.items():
            self.variables[f"#{5061 + 'XYZABC'.index(a)}"] = v

    def lookup(self, name: str) -> float | str:
        if name.startswith("#") and name[1:].isdigit():
            n = int(name[1:])
            for base in (5001, 5021, 5041):
                if base <= n < base + 6:
                    return self.io.position().get("XYZABC"[n - base], 0.0)
        return super().lookup(name)


def make_interpreter(dialect: str, io: MachineIO, variables: dict | None = None,
                     **options: Any) -> Any:
    """An interpreter for ``dialect`` (one of ``DIALECTS``) driving ``io``."""
    variables = {} if variables is None else variables
    if dialect == "fanuc":
        return FanucInterpreter(io, variables)
    if dialect == "haas":
        return HaasInterpreter(io, variables, name="haas")
    if dialect == "linuxcnc":
        variables.setdefault("#<_task>", 1.0)  # real execution, not a preview
        return LinuxcncInterpreter(io, variables)
    if dialect == "siemens":
        return SiemensInterpreter(io, variables)
    if dialect == "heidenhain":
        return HeidenhainInterpreter(io, variables, **options)
    raise ValueError(f"unknown dialect {dialect!r}; expected one of {', '.join(DIALECTS)}")


__all__ = ["DIALECTS", "Alarm", "BlockQueue", "MachineIO", "ProbeOutcome", "make_interpreter",
           "run"]
