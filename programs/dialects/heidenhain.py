"""The Heidenhain TNC conversational dialect."""

from __future__ import annotations

import math
import re
from collections.abc import Sequence

from contracts.result_lines import SLOT_FIELDS, VERDICT_VARIABLES
from programs.cycletime import CycleTime
from programs.dialects.base import Code, Dialect, sfmt
from programs.model import Program, Touch


class Heidenhain(Dialect):
    """Heidenhain TNC conversational: TCH PROBE 0/1/4, Q115-Q119, FN 16 F-PRINT, FN 14 ERROR."""

    name, extension, counter, slot_prefix, slot_base = "heidenhain", "h", "Q1599", "Q", 1600
    result_print = re.compile(r"FN 16: F-PRINT RUMBA_")
    tcpm_off, tcpm_note = "M129", "M128 FUNCTION TCPM MUST BE OFF - M129 BELOW"
    linear_rapid = True  # L ... FMAX: a straight line at rapid traverse
    result_channel = "FN 16 F-PRINT to RUMBA_RES.TXT next to the program"
    print_base = 1580
    verdict_variable = VERDICT_VARIABLES["heidenhain"]

    def _verdict_lines(self, code: int) -> list[str]:
        return ["0 BEGIN PGM RUMBAV MM", f"1 {self.verdict_variable} = +{code}",
                "2 END PGM RUMBAV MM"]

    def sources(self, program: Program) -> list[str]:
        return ["TRIG", "Q115", "Q116", "Q117", "Q118", "Q119"]

    def words(self, letters: Sequence[str], values: Sequence[float]) -> str:
        return Code(" ".join(f"{a}{sfmt(v)}" for a, v in zip(letters, values, strict=True)))

    def touch_context(self, program: Program, t: Touch) -> dict:
        ctx = super().touch_context(program, t)
        d = [e - s for e, s in zip(t.end, t.start, strict=True)]
        n = math.sqrt(sum(x * x for x in d))
        u = [x / n for x in d]
        if abs(u[2]) < 1e-9:
            ctx["cycle"] = 1
            ctx["angle"] = sfmt(math.degrees(math.atan2(u[1], u[0])) % 360.0)
        elif abs(abs(u[k := max(range(3), key=lambda i: abs(u[i]))]) - 1.0) <= 1e-9:
            ctx["cycle"] = 0
            ctx["axis"] = "XYZ"[k] + ("+" if u[k] > 0 else "-")
        else:
            # a tilted probe: cycle 4 MEASURING IN 3-D probes from where the tool is
            # (the start point) along IX IY IZ for ABST and writes X Y Z to Q115-Q117; it leaves
            # the rotary axes alone, which stand at the pose (Q118, Q119 set from it)
            ctx["cycle"] = 4
            ctx["dir"] = [sfmt(x) for x in u]
            ctx["dist"] = f"{n:.4f}"
            ctx["rot"] = [sfmt(t.b_deg), sfmt(t.c_deg)]
        ctx["print"] = [Code(f"Q{self.print_base + f}") for f in range(SLOT_FIELDS)]
        ctx["format_file"] = Code(f"RUMBA_{t.id.ball}.A")  # checked by touch_context
        return ctx

    def render(self, program: Program, cycle_time: CycleTime | None = None) -> str:
        text = super().render(program, cycle_time)
        lines = text.rstrip("\n").split("\n")
        return "\n".join(f"{i} {line}" for i, line in enumerate(lines)) + "\n"

    def aux_files(self, program: Program) -> dict[str, str]:
        out = {}
        q = [f"Q{self.print_base + f}" for f in range(SLOT_FIELDS) if f != 3]
        for b in program.artefact.balls:
            self.check_ball_id(b.id)  # inside a quoted format string and a file name
            fmt_ = ("RUMBA %.0LF %.0LF %.0LF " + b.id
                    + " %.0LF %.0LF %.4LF %.4LF %.4LF %.4LF %.4LF\\n")
            out[f"RUMBA_{b.id}.A"] = f'"{fmt_}", ' + ", ".join(q) + ";\n"
        if program.temperature_vars:  # pose Q1591, channel Q1592, value Q1593
            self.temperature_prints(program)  # checked before any file is written
            for marker, head, args in (("S", "S", ""), ("P", "P%.0LF", "Q1591, "),
                                       ("E", "E", "")):
                out[f"RTEMP_{marker}.A"] = (f'"RTEMP {head} %.0LF %.3LF\\n", {args}'
                                             "Q1592, Q1593;\n")
        return out
