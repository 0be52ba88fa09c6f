"""The Sinumerik 840D dialect."""

from __future__ import annotations

import re

from contracts.result_lines import VERDICT_VARIABLES
from programs.dialects.base import Dialect
from programs.model import Program


class Siemens(Dialect):
    """Sinumerik 840D: MEAS=1 G1, $AA_MW / $AC_MEA, R parameters, WRITE, SETAL."""

    name, extension, counter, slot_prefix, slot_base = "siemens", "mpf", "R99", "R", 100
    result_print = re.compile(r'WRITE\(RERR,"RUMBA_RES",RLINE\)')
    result_armed = re.compile(r'RLINE="RUMBA ')
    tcpm_off, tcpm_note = "TRAFOOF", "TRAORI MUST BE OFF - TRAFOOF BELOW"
    # RTLION: G0 interpolates linearly, all path axes arrive together (SINUMERIK programming
    # manual 12/2019 §2.9; RTLIOF, or MD20730 G0_LINEAR_MODE = 0, would make it non-linear)
    linear_rapid, linear_rapid_on = True, "RTLION"
    result_channel = "WRITE to the file RUMBA_RES (part-program memory)"
    verdict_variable = VERDICT_VARIABLES["siemens"]

    def _verdict_lines(self, code: int) -> list[str]:
        return ["; RUMBA VERDICT", f"{self.verdict_variable}={code}", "M30"]

    def sources(self, program: Program) -> list[str]:
        return ["$AC_MEA[1]", "$AA_MW[X]", "$AA_MW[Y]", "$AA_MW[Z]",
                *(f"$AA_IW[{a}]" for a in program.rotary)]
