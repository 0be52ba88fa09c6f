"""Heidenhain TNC conversational dialect: numbered lines, Q parameters, L moves, touch-probe
cycles 0 (REF. PLANE), 1 (POLAR DATUM PLANE) and 4 (MEASURING IN 3-D), FN 9-12 jumps, FN 14
errors, FN 16 F-PRINT (to the DNC line and to its target file), FN 18 SYSREAD ID360 (last touch
point), CALL PGM of a straight-line program (a stop or verdict program rumba writes).

Touch-probe cycles behave as the TNC manuals describe them: the point given in ``0.1`` / ``1.2``
is the PRE-POSITION, approached at the probe table's FMAX; the probe then moves along the
probing direction at the probe table feed for at most the measuring path (DIST) and stops with
an error when the stylus is not deflected; the trigger position goes to Q115-Q119 (X Y Z 4th
5th, cycle 0 also to its result parameter), and the probe retracts to the pre-position.
"""

from __future__ import annotations

import math
import re

from simulators.gcode.core import END, NEXT, Alarm, Flow, Interpreter

_LINE_NO = re.compile(r"^\s*\d+\s+")
_Q = r"(?:QL|QR|Q)\d+"
_ASSIGN = re.compile(rf"^(?:FN\s*0\s*:\s*)?({_Q})\s*=\s*(.+)$", re.IGNORECASE)
_FN_JUMP = re.compile(r"^FN\s*(9|10|11|12)\s*:\s*IF\s+(.+?)\s+(EQU|NE|GT|LT)\s+(.+?)\s+"
                      r"GOTO\s+LBL\s+(\w+)$", re.IGNORECASE)
_LBL = re.compile(r"^LBL\s+(\w+)$", re.IGNORECASE)
_WORD = re.compile(rf"\s*([A-Z])\s*([-+]?(?:\d+\.?\d*|\.\d+)|[-+]?{_Q})", re.IGNORECASE)
_FPRINT = re.compile(r"^FN\s*16\s*:\s*F-PRINT\s+(\S+)\s*/\s*(\S+)$", re.IGNORECASE)
_CALL_PGM = re.compile(r"^CALL\s+PGM\s+(\S+)$", re.IGNORECASE)
_FMT_LINE = re.compile(r'^\s*"((?:[^"\\]|\\.)*)"\s*(?:,(.*?))?\s*;?\s*$')
_FMT_SPEC = re.compile(r"%(-?\d*(?:\.\d+)?)(LF|F|D|I|S)", re.IGNORECASE)
_CMP = {"EQU": lambda a, b: a == b, "NE": lambda a, b: a != b,
        "GT": lambda a, b: a > b, "LT": lambda a, b: a < b}


class HeidenhainInterpreter(Interpreter):
    def __init__(self, io, variables=None, name: str = "heidenhain", *,
                 files: dict[str, str] | None = None, measuring_path_mm: float = 4.0,
                 probe_feed_mm_min: float = 300.0, stylus_radius_mm: float = 3.0) -> None:
        super().__init__(io, variables if variables is not None else {}, name=name)
        self.files = files if files is not None else {}
        self.measuring_path_mm = measuring_path_mm
        self.probe_feed_mm_min = probe_feed_mm_min
        self.pending: dict[str, object] | None = None
        self.last_touch: tuple[dict[str, float], list[float]] | None = None
        self.stylus_radius_mm = stylus_radius_mm

    def _code(self, block: str) -> str:
        code = _LINE_NO.sub("", block, count=1)
        return code.split(";", 1)[0].strip()

    def lookup(self, name: str) -> float | str:
        return self.variables.get(name.upper(), 0.0)

    def label_of(self, block: str) -> str | None:
        m = _LBL.match(self._code(block))
        return m.group(1).upper() if m else None

    def execute(self, block: str, index: int) -> Flow:
        code = self._code(block)
        if not code:
            return NEXT
        up = code.upper()
        if up.startswith("BEGIN PGM"):
            return NEXT
        if up.startswith("END PGM"):
            return END
        if _LBL.match(code):
            return END if self.label_of(block) == "0" else NEXT
        m = _ASSIGN.match(code)
        if m:
            self.variables[m.group(1).upper()] = self.num(m.group(2))
            return NEXT
        m = _FN_JUMP.match(code)
        if m:
            a, b = self.num(m.group(2)), self.num(m.group(4))
            return Flow("goto", label=m.group(5).upper()) if _CMP[m.group(3).upper()](a, b) \
                else NEXT
        m = re.match(r"^FN\s*14\s*:\s*ERROR\s*=\s*(.+)$", code, re.IGNORECASE)
        if m:
            raise Alarm(f"FN 14 error {int(self.num(m.group(1)))}")
        m = re.match(rf"^FN\s*18\s*:\s*SYSREAD\s+({_Q})\s*=\s*ID\s*360\s+NR\s*(\d+)\s+"
                     r"IDX\s*(\d+)$", code, re.IGNORECASE)
        if m:
            self.variables[m.group(1).upper()] = self.sysread_360(int(m.group(2)),
                                                                  int(m.group(3)))
            return NEXT
        m = _FPRINT.match(code)
        if m:
            for line in self.fprint(m.group(1)):
                self.io.output(line, target=m.group(2))
            return NEXT
        m = _CALL_PGM.match(code)
        if m:
            self.call_pgm(m.group(1))
            return NEXT
        if up.startswith("TCH PROBE"):
            return self.touch_probe(code)
        if up.startswith("CYCL DEF 9.0"):
            return NEXT
        m = re.match(r"^CYCL DEF 9\.1\s+DWELL\s+(.+)$", code, re.IGNORECASE)
        if m:
            self.io.dwell(self.num(m.group(1)))
            return NEXT
        if up.startswith("TOOL CALL"):
            self.io.dwell(5.0)
            return NEXT
        if up == "STOP":
            return Flow("stop")
        if re.match(r"^L(\s|$)", up):
            return self.linear(code[1:])
        if re.fullmatch(r"M\d+", up):
            return self.mcode(int(up[1:]))
        raise Alarm(f"not supported by this controller model: {code!r}")

    def mcode(self, m: int) -> Flow:
        if m in (2, 30):
            return END
        if m == 0:
            return Flow("stop")
        return NEXT

    def _words(self, text: str) -> tuple[dict[str, float], list[str]]:
        vals, rest = {}, []
        for tok in text.split():
            if tok.upper() in ("FMAX", "R0", "RL", "RR", "FAUTO"):
                rest.append(tok.upper())
                continue
            m = _WORD.fullmatch(tok)
            if not m:
                raise Alarm(f"cannot read {tok!r}")
            vals[m.group(1).upper()] = self.num(m.group(2))
        return vals, rest

    def linear(self, text: str) -> Flow:
        vals, rest = self._words(text)
        axes = self.axis_words({k: v for k, v in vals.items() if k in "XYZABCUVW"})
        if "F" in vals:
            if vals["F"] <= 0:
                raise Alarm("feed rate must be positive")
            self.modal.feed_mm_min = vals["F"]
            self.modal.motion = "G1"
        if "FMAX" in rest:
            feed = None
        else:
            if self.modal.feed_mm_min <= 0:
                raise Alarm("L without a feed rate")
            feed = self.modal.feed_mm_min
        if axes:
            self.io.move(self.target(axes), feed)
        if "M" in vals:
            return self.mcode(int(vals["M"]))
        return NEXT

    def touch_probe(self, code: str) -> Flow:
        m = re.match(r"^TCH PROBE\s+(\d+)\.(\d+)\s*(.*)$", code, re.IGNORECASE)
        if not m:
            raise Alarm(f"bad TCH PROBE block {code!r}")
        cyc, step, rest = int(m.group(1)), int(m.group(2)), m.group(3).strip()
        if cyc == 0 and step == 0:
            mm = re.match(rf"^REF\.?\s*PLANE\s+({_Q})\s+([XYZ])([-+])$", rest, re.IGNORECASE)
            if not mm:
                raise Alarm(f"TCH PROBE 0.0: expected 'REF. PLANE Q<n> <axis><sign>': {rest!r}")
            d = [0.0, 0.0, 0.0]
            d["XYZ".index(mm.group(2).upper())] = 1.0 if mm.group(3) == "+" else -1.0
            self.pending = {"cycle": 0, "result": mm.group(1).upper(), "dir": d,
                            "axis": mm.group(2).upper()}
            return NEXT
        if cyc == 1 and step == 0:
            self.pending = {"cycle": 1}
            return NEXT
        if cyc == 1 and step == 1:
            mm = re.match(r"^([XYZ])\s+ANGLE\s*:\s*(.+)$", rest, re.IGNORECASE)
            if not mm or not self.pending or self.pending.get("cycle") != 1:
                raise Alarm(f"TCH PROBE 1.1 out of sequence or malformed: {rest!r}")
            if mm.group(1).upper() != "X":
                raise Alarm("TCH PROBE 1.1: only reference axis X is used")
            a = math.radians(self.num(mm.group(2)))
            self.pending["dir"] = [math.cos(a), math.sin(a), 0.0]
            return NEXT
        if cyc == 4:
            return self._cycle4(step, rest)
        if (cyc, step) in ((0, 1), (1, 2)):
            if not self.pending or self.pending.get("cycle") != cyc or "dir" not in self.pending:
                raise Alarm(f"TCH PROBE {cyc}.{step} without its cycle definition")
            vals, _ = self._words(rest)
            pre = self.target(self.axis_words(vals))
            self.io.move(pre, None)  # pre-position at the probe table's FMAX
            d = self.pending["dir"]
            end = dict(pre)
            for k, a in enumerate("XYZ"):
                end[a] = pre[a] + self.measuring_path_mm * d[k]
            out = self.io.probe(end, self.probe_feed_mm_min)
            if not out.triggered:
                raise Alarm("TOUCH POINT INACCESSIBLE (stylus not deflected within the "
                            "measuring path)")
            for k, a in enumerate(self.io.axes):
                self.variables[f"Q{115 + k}"] = out.latched[a]
            self.last_touch = (dict(out.latched), list(d))
            if cyc == 0:
                self.variables[str(self.pending["result"])] = out.latched[self.pending["axis"]]
            self.io.move(pre, None)  # retract to the starting point
            self.pending = None
            return NEXT
        raise Alarm(f"TCH PROBE {cyc}.{step} is not supported by the simulator")

    def _cycle4(self, step: int, rest: str) -> Flow:
        """Cycle 4 MEASURING IN 3-D: from the current position along the direction of 4.2 for at
        most ABST at F; X Y Z of the trigger to Q<n>..Q<n+2> of 4.1; back by at most MB."""
        if step == 0:
            if not re.match(r"^MEASURING\s+IN\s+3-?D$", rest, re.IGNORECASE):
                raise Alarm(f"TCH PROBE 4.0: expected 'MEASURING IN 3-D': {rest!r}")
            self.pending = {"cycle": 4}
            return NEXT
        if not self.pending or self.pending.get("cycle") != 4:
            raise Alarm(f"TCH PROBE 4.{step} without its cycle definition")
        if step == 1:
            mm = re.match(r"^Q(\d+)$", rest, re.IGNORECASE)
            if not mm:
                raise Alarm(f"TCH PROBE 4.1: expected 'Q<n>': {rest!r}")
            self.pending["result"] = int(mm.group(1))
            return NEXT
        if step == 2:
            inc = dict(re.findall(r"I([XYZ])\s*([-+]?[\d.]+)", rest.upper()))
            d = [float(inc.get(a, 0.0)) for a in "XYZ"]
            n = math.sqrt(sum(x * x for x in d))
            if n == 0:
                raise Alarm(f"TCH PROBE 4.2: no direction in {rest!r}")
            self.pending["dir"] = [x / n for x in d]
            return NEXT
        mm = re.match(r"^ABST\s*\+?([\d.]+)\s+F([\d.]+)\s+MB\s*\+?([\d.]+)"
                      r"\s+REFERENCE\s+SYSTEM\s*:\s*0$", rest, re.IGNORECASE)
        if step != 3 or not mm or "dir" not in self.pending or "result" not in self.pending:
            raise Alarm(f"TCH PROBE 4.{step} out of sequence or malformed: {rest!r}")
        dist, feed, back = (float(mm.group(i)) for i in (1, 2, 3))
        start = dict(self.io.position())
        d = self.pending["dir"]
        end = dict(start)
        for k, a in enumerate("XYZ"):
            end[a] = start[a] + dist * d[k]
        out = self.io.probe(end, feed)
        if not out.triggered:
            raise Alarm("TOUCH POINT INACCESSIBLE (stylus not deflected within ABST)")
        q = int(self.pending["result"])
        for k, a in enumerate("XYZ"):
            self.variables[f"Q{q + k}"] = out.latched[a]
        self.last_touch = (dict(out.latched), list(d))
        run = math.sqrt(sum((out.latched[a] - start[a]) ** 2 for a in "XYZ"))
        s = min(back, run) / run if run > 0 else 0.0
        self.io.move({**out.latched, **{a: out.latched[a] - s * (out.latched[a] - start[a])
                                        for a in "XYZ"}}, None)
        self.pending = None
        return NEXT

    def sysread_360(self, nr: int, idx: int) -> float:
        """FN 18 ID360: last touch point of cycle 0/1 for axis ``idx`` (1 = X … 5 = 5th axis);
        NR1 with the stylus radius compensated (the surface point), NR2/NR3 the stylus centre
        (no compensation)."""
        if self.last_touch is None:
            raise Alarm("FN 18 ID360: no touch-probe result yet")
        if not 1 <= idx <= len(self.io.axes) or nr not in (1, 2, 3):
            raise Alarm(f"FN 18 ID360 NR{nr} IDX{idx} is not simulated")
        latched, d = self.last_touch
        v = latched[self.io.axes[idx - 1]]
        if nr == 1 and idx <= 3:
            v += self.stylus_radius_mm * d[idx - 1]
        return v

    def call_pgm(self, path: str) -> None:
        """CALL PGM: the called program runs now (read from the control's files when it is
        called, as a file written meanwhile takes effect); simulated for straight-line programs
        (Q assignments, comments): a verdict or stop program."""
        name = path.split("\\")[-1].split("/")[-1].upper()
        text = next((t for n, t in self.files.items() if n.upper() == name), None)
        if text is None:
            raise Alarm(f"CALL PGM {path}: program not found on the control")
        for block in text.replace("\r\n", "\n").split("\n"):
            code = self._code(block)
            if not code or code.upper().startswith(("BEGIN PGM", "END PGM")):
                continue
            m = _ASSIGN.match(code)
            if not m:
                raise Alarm(f"CALL PGM {name}: {code!r} is not simulated in a called program")
            self.variables[m.group(1).upper()] = self.num(m.group(2))

    def fprint(self, fmt_file: str) -> list[str]:
        name = fmt_file.split("\\")[-1].split("/")[-1]
        text = self.files.get(name)
        if text is None:
            raise Alarm(f"FN 16: format file {name} not found on the control")
        out: list[str] = []
        buf = ""
        for raw in text.splitlines():
            if not raw.strip():
                continue
            m = _FMT_LINE.match(raw)
            if not m:
                raise Alarm(f"FN 16: {name}: cannot read {raw.strip()!r}")
            fmt = m.group(1)
            args = [a.strip() for a in (m.group(2) or "").split(",") if a.strip()]
            buf += _cformat(fmt, [self.num(a) for a in args])
        buf = buf.replace("\\n", "\n")
        out += [ln for ln in buf.split("\n") if ln]
        return out


def _cformat(fmt: str, args: list[float]) -> str:
    out, pos = [], 0
    for k, m in enumerate(_FMT_SPEC.finditer(fmt)):
        out.append(fmt[pos:m.start()])
        if k >= len(args):
            raise Alarm(f"FN 16: too few values for {fmt!r}")
        conv = m.group(2).upper()
        spec = m.group(1)
        v = args[k]
        out.append(format(round(v), spec + "d") if conv in ("D", "I")
                   else format(v, spec + "f"))
        pos = m.end()
    out.append(fmt[pos:])
    return "".join(out)
