"""The LinuxCNC 2.9 dialect."""

from __future__ import annotations

import re

import numpy as np

from contracts.result_lines import VERDICT_VARIABLES
from programs.cycletime import CycleTime
from programs.dialects.base import Code, Dialect, fmt
from programs.model import Program


class LinuxCNC(Dialect):
    """LinuxCNC 2.9: G38.2 (two-speed: G38.3, G1 back-off, G38.2), #5061-#5070, (LOG,…), O-word
    miss check guarded by #<_task>."""

    name, extension, counter, slot_prefix, slot_base = "linuxcnc", "ngc", "#3999", "#", 4000
    result_print = re.compile(r"\(LOG,RUMBA ")
    tcpm_off, tcpm_note = "G49", "TCP KINEMATICS MUST BE OFF - IDENTITY JOINT MODE, G49 BELOW"
    linear_rapid = True  # G0 is a coordinated straight line: every axis arrives together
    log_file = "rumba_results.log"
    result_channel = f"(LOG,…) lines in {log_file} (LinuxCNC's working directory)"
    verdict_variable = VERDICT_VARIABLES["linuxcnc"]

    def _verdict_lines(self, code: int) -> list[str]:
        return ["%", "(RUMBA VERDICT)", f"{self.verdict_variable} = {code}", "M2", "%"]

    two_speed = True  # G38.3 locates (no error on a miss), G1 backs off, G38.2 re-touches

    def backoff_words(self, offset_mm: np.ndarray) -> str:
        return Code(" ".join(f"{a}[#{5061 + i}{'-' if d < 0 else '+'}{fmt(abs(d))}]"
                             for i, (a, d) in enumerate(zip("XYZ", offset_mm, strict=True))))

    def sources(self, program: Program) -> list[str]:
        rot = [f"#{5061 + 'XYZABC'.index(a)}" for a in program.rotary]
        return ["#5070", "#5061", "#5062", "#5063", *rot]

    def context(self, program: Program, cycle_time: CycleTime) -> dict:
        return {**super().context(program, cycle_time), "log_file": self.log_file}
