"""The one way to a program: build the tool path, check it, render it, time it."""

from __future__ import annotations

from dataclasses import dataclass

from contracts.setup_files import MachineFile, Plan
from contracts.touch_table import TouchTable
from identification.kinematics import Machine
from identification.model import Artefact
from programs.cycletime import CycleTime, estimate
from programs.dialects import Dialect, get_dialect
from programs.model import Program, Targets, Touch
from programs.safety import SafetyReport, check_program
from programs.toolpath import build_program


@dataclass
class GeneratedProgram:
    """A checked program ready for a link: text, auxiliary files, safety report and times."""

    program: Program
    dialect: Dialect  # the dialect that rendered ``text`` (it decodes the result lines)
    text: str
    aux_files: dict[str, str]
    safety: SafetyReport
    cycle_time: CycleTime

    @property
    def touches(self) -> list[Touch]:
        return self.program.touches

    @property
    def estimated_s(self) -> float:
        return self.cycle_time.estimate_s

    @property
    def lower_bound_s(self) -> float:
        return self.cycle_time.lower_bound_s

    def touch_table(self) -> TouchTable:
        """The touch table of the program (what names and completes every result)."""
        return self.program.touch_table()


def generate(machine: Machine, machine_file: MachineFile, artefact: Artefact, plan: Plan,
             dialect: str, targets: Targets | None = None,
             temperature_vars: tuple[str, ...] = (), handshake: bool = False
             ) -> GeneratedProgram:
    """Build, check (``programs.safety.SafetyError`` when unsafe), render and time a program;
    ``programs.geometry.ProgramError`` when the plan cannot become one. The cycle time is
    computed once: the program's header prints the same estimate the result carries.
    ``temperature_vars``: macro variables to print (temperature channels over DNC);
    ``handshake``: the ring wait and stop check of a link reading the controller's variables
    (``contracts.result_lines.HANDSHAKE_VARIABLES``)."""
    d = get_dialect(dialect)
    prog = build_program(machine, machine_file, artefact, plan, targets, two_speed=d.two_speed)
    prog.temperature_vars = tuple(temperature_vars)
    prog.handshake = handshake
    report = check_program(prog)
    ct = estimate(prog, d.linear_rapid)
    text = d.render(prog, ct)
    return GeneratedProgram(prog, d, text, d.aux_files(prog), report, ct)
