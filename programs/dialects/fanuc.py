"""The Fanuc macro B dialect (also Haas)."""

from __future__ import annotations

import re

from contracts.result_lines import VERDICT_VARIABLES
from programs.cycletime import CycleTime
from programs.dialects.base import Dialect
from programs.geometry import ProgramError
from programs.model import Program


class Fanuc(Dialect):
    """Fanuc 0i/30i macro B (also Haas): G31, #5061-#5065, DPRNT, #3000 alarm."""

    name, extension, counter, slot_prefix, slot_base = "fanuc", "nc", "#599", "#", 600
    result_print = re.compile(r"DPRNT\[RUMBA\*")
    tcpm_off, tcpm_note = "G49", "G43.4 G43.5 TCPM MUST BE OFF - G49 BELOW"
    result_channel = "DPRNT on the DNC serial port (POPEN/PCLOS)"
    verdict_variable = VERDICT_VARIABLES["fanuc"]
    verdict_program_number = 9101

    def _verdict_lines(self, code: int) -> list[str]:
        return ["%", f"O{self.verdict_program_number} (RUMBA VERDICT)",
                f"{self.verdict_variable}={code}.", "M30", "%"]

    def __init__(self, haas: bool = False) -> None:
        super().__init__()
        self.haas = haas
        if haas:  # Haas: TCPC is G234; G49 cancels it as it does G43.4
            self.tcpm_note = "G234 TCPC G43.4 MUST BE OFF - G49 BELOW"

    @property
    def label(self) -> str:
        return "haas" if self.haas else super().label

    def check_ball_id(self, ball: str) -> None:
        if not re.fullmatch(r"[A-Z0-9]{1,12}", ball):
            raise ProgramError(f"ball id {ball!r}: the fanuc dialect needs [A-Z0-9]{{1,12}} "
                               "(Fanuc program text and DPRNT have no lower case or '_')")

    def sources(self, program: Program) -> list[str]:
        if self.haas:
            rot = [f"#{5061 + 'XYZABC'.index(a)}" for a in program.rotary]
        else:
            rot = ["#5064", "#5065"]  # 4th and 5th axis = first and second rotary letter
        return ["1.", "#5061", "#5062", "#5063", *rot]

    program_number = 9100
    stop_block = 99998  # the handshake's end at a stop request: above every move number

    def context(self, program: Program, cycle_time: CycleTime) -> dict:
        ctx = super().context(program, cycle_time)
        ctx["info"] = [x.upper() for x in ctx["info"]]
        if ctx["handshake"] and any(b.n >= self.stop_block for b in ctx["blocks"]):
            raise ProgramError(f"program of {len(ctx['blocks'])} moves: its block numbers "
                               f"reach N{self.stop_block}, the handshake's stop block")
        return {**ctx, "program_number": self.program_number, "stop_block": self.stop_block}
