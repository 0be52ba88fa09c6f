"""Fanuc / Haas dialect: macro B (#vars, IF/GOTO, WHILE/DO/END), G31 skip, DPRNT, #3000 alarms.

Skip results follow the controllers: ``#5061``-``#5065`` hold X, Y, Z, 4th, 5th at the skip
signal — and the END POINT of the move when nothing triggered (Haas and Fanuc alike), so a
program must never infer "triggered" from the position alone. Comments are ``( … )``.

Compensation writes reach the control's kinematic values (``io.kinematics``,
simulators/controller_kinematics.py), never the truth: ``G10 L52`` … ``N<param> R<value>`` …
``G11`` (programmable parameter input) writes a real-type parameter the Fanuc section declares;
the value needs its decimal point (without one a real control reads least input increments: the
simulator refuses it rather than guess the increment). A parameter the control does not hold, an
axis-type ``P`` word, or ``G10 L52`` on a control without a Fanuc section (Haas: settings are
entered by hand, ``VirtualController.operator_entry``) raises an alarm, as a control rejects a
parameter. A macro variable the section declares (``#500``) reads and writes the kinematic value.
"""

from __future__ import annotations

import re

from contracts.dialects import dialect
from simulators.gcode.core import END, NEXT, Alarm, Flow, Interpreter, split_words

_COMMENT = re.compile(r"\([^)]*\)")
_N = re.compile(r"^\s*N\s*(\d+)\s*", re.IGNORECASE)
_IF_GOTO = re.compile(r"^IF\s*(\[.*\])\s*GOTO\s*(.+)$", re.IGNORECASE)
_IF_THEN = re.compile(r"^IF\s*(\[.*\])\s*THEN\s*(.+)$", re.IGNORECASE)
_GOTO = re.compile(r"^GOTO\s*(.+)$", re.IGNORECASE)
_WHILE = re.compile(r"^WHILE\s*(\[.*\])\s*DO\s*(\d+)$", re.IGNORECASE)
_END = re.compile(r"^END\s*(\d+)$", re.IGNORECASE)
_ASSIGN = re.compile(r"^(#\s*(?:\d+|\[.*?\]))\s*=\s*(.+)$", re.IGNORECASE)
_DPRNT = re.compile(r"^DPRNT\s*\[(.*)\]$", re.IGNORECASE)
_PARAM = re.compile(r"^N\s*(\d+)\s*(P\s*\d+\s*)?R\s*([-+]?[0-9.]+)$", re.IGNORECASE)
_DPRNT_VAR = re.compile(r"#(\d+|\[[^\]]*\])\s*\[\s*(\d)\s*(\d)\s*\]")

# G codes that only set modes our moves do not depend on (planes, compensation off, canned
# cycle cancel, work offsets at zero, feed per minute, tool length compensation on).
_MODAL_NOOP = {15.0, 17.0, 18.0, 19.0, 40.0, 43.0, 49.0, 50.0, 54.0, 55.0, 56.0, 57.0, 58.0,
               59.0, 64.0, 67.0, 69.0, 80.0, 94.0, 98.0, 99.0, 54.1}


def _clean(block: str) -> tuple[str, str]:
    """(code without comments, the comment text)."""
    comments = " ".join(c[1:-1] for c in _COMMENT.findall(block))
    code = _COMMENT.sub("", block).strip()
    if code.startswith("/"):  # block delete switch off: the block is executed
        code = code[1:].strip()
    return code, comments.strip()


class FanucInterpreter(Interpreter):
    """Fanuc 0i/30i macro B and Haas NGC (same words, same skip variables)."""

    probe_g = 31.0
    miss_alarm = False

    def __init__(self, io, variables=None, name: str = "fanuc") -> None:
        super().__init__(io, variables if variables is not None else {}, name=name)
        self.parameter_input = False  # between G10 L52 and G11

    def kinematic_address(self, address: str) -> bool:
        """Does the control keep ``address`` as a Fanuc kinematic value?"""
        store = getattr(self.io, "kinematics", None)
        return (store is not None
                and dialect(store.family).kinematics_address == "parameter_or_macro"
                and store.holds(address))

    def parameter_block(self, raw: str) -> Flow:
        """One block of G10 L52 mode: ``N<param> R<value>`` or the closing ``G11``."""
        code = raw.replace(" ", "").upper()
        if code in ("G11", "G11.0"):
            self.parameter_input = False
            return NEXT
        m = _PARAM.match(code)
        if not m:
            raise Alarm(f"G10 L52: {raw!r} is not N<parameter> R<value> (or G11)")
        n, axis, text = int(m.group(1)), m.group(2), m.group(3)
        if axis:
            raise Alarm(f"G10 L52: parameter {n} P: axis-type parameters are not simulated")
        if not self.kinematic_address(str(n)):
            raise Alarm(f"G10 L52: parameter {n} is not available (not a kinematic parameter "
                        "of this control)")
        if "." not in text:
            raise Alarm(f"G10 L52: parameter {n} R{text}: a real-type value needs its "
                        "decimal point")
        self.io.kinematics.write(str(n), float(text), "G10 L52")
        return NEXT

    # ------------------------------------------------------------------ variables
    def lookup(self, name: str) -> float | str:
        if name.startswith("#"):
            n = int(name[1:])
            pos = self.io.position()
            axes = self.io.axes
            for base in (5001, 5021, 5041):  # block end, machine, current position
                if base <= n < base + len(axes):
                    return pos[axes[n - base]]
            if n == 0:
                return 0.0  # #0 is <vacant>, read as 0 in arithmetic
            if self.kinematic_address(name):
                return self.io.kinematics.read(name)
        return self.variables.get(name, 0.0)

    def assign(self, target: str, value: float) -> None:
        t = target.replace(" ", "")
        idx = round(self.num(t[2:-1])) if t.startswith("#[") else int(t[1:])
        if idx == 3000:
            raise Alarm(f"#3000 alarm {3000 + int(value)}")
        if idx in range(1, 34) or idx >= 100:
            self.variables[f"#{idx}"] = float(value)
            if self.kinematic_address(f"#{idx}"):
                self.io.kinematics.write(f"#{idx}", float(value), f"#{idx}=")
        else:
            raise Alarm(f"#{idx} cannot be written (system variable)")

    # ------------------------------------------------------------------ structure
    def _code(self, block: str) -> str:
        code, _ = _clean(block)
        return _N.sub("", code, count=1).strip()

    def label_of(self, block: str) -> str | None:
        m = _N.match(_clean(block)[0])
        return f"N{int(m.group(1))}" if m else None

    def structure(self, block: str) -> tuple[str, str] | None:
        code = self._code(block)
        m = _WHILE.match(code)
        if m:
            return ("while", m.group(2))
        m = _END.match(code)
        if m:
            return ("endwhile", m.group(1))
        return None

    def condition(self, block: str) -> bool:
        m = _WHILE.match(self._code(block))
        return bool(self.num(m.group(1))) if m else False

    # ------------------------------------------------------------------ execution
    def execute(self, block: str, index: int) -> Flow:
        raw, comment = _clean(block)
        if self.parameter_input and raw:
            return self.parameter_block(raw)
        if raw == "%":
            return NEXT if index == 0 else END
        code = _N.sub("", raw, count=1).strip()
        if not code or re.fullmatch(r"O\d+", code, re.IGNORECASE):
            return NEXT
        return self._statement(code, comment, index)

    def _statement(self, code: str, comment: str, index: int) -> Flow:
        up = code.upper()
        if up.startswith("IF"):
            m = _IF_GOTO.match(code)
            if m:
                if self.num(m.group(1)):
                    return Flow("goto", label=f"N{int(self.num(m.group(2)))}")
                return NEXT
            m = _IF_THEN.match(code)
            if m:
                if self.num(m.group(1)):
                    return self._statement(m.group(2).strip(), comment, index)
                return NEXT
            raise Alarm(f"bad IF statement {code!r}")
        m = _GOTO.match(code)
        if m:
            return Flow("goto", label=f"N{int(self.num(m.group(1)))}")
        m = _DPRNT.match(code)
        if m:
            self.io.output(self.dprnt(m.group(1)))
            return NEXT
        if up in ("POPEN", "PCLOS", "BPRNT"):
            return NEXT
        m = _ASSIGN.match(code)
        if m and m.group(1).replace(" ", "") == "#3006":  # stop with a message (cycle start)
            self.io.message(f"{int(self.num(m.group(2)))} {comment}".strip())
            return Flow("stop")
        if m:
            value = self.num(m.group(2))
            try:
                self.assign(m.group(1), value)
            except Alarm as e:
                raise Alarm(f"{e} {comment}".strip()) from None
            return NEXT
        return self.words(code)

    def dprnt(self, body: str) -> str:
        """Fanuc DPRNT: ``*`` prints a space, ``#v[ab]`` a value with a integer digits and b
        decimals (leading zeros suppressed, '-' only for negatives), letters as they are."""
        out, pos = [], 0
        for m in _DPRNT_VAR.finditer(body):
            out.append(body[pos:m.start()].replace("*", " "))
            ref = m.group(1)
            v = float(self.lookup(f"#{round(self.num(ref[1:-1]))}" if ref.startswith("[")
                                  else f"#{ref}"))
            dec = int(m.group(3))
            s = f"{v:.{dec}f}"
            if float(s) == 0.0:
                s = s.lstrip("-")
            out.append(s)
            pos = m.end()
        out.append(body[pos:].replace("*", " "))
        return "".join(out)

    def words(self, code: str) -> Flow:
        pairs = split_words(code)
        gs: list[float] = []
        ms: list[int] = []
        vals: dict[str, float] = {}
        raw: dict[str, str] = {}
        for letter, text in pairs:
            v = self.num(text)
            if letter == "G":
                gs.append(round(v, 1))
            elif letter == "M":
                ms.append(int(v))
            else:
                if letter in vals:
                    raise Alarm(f"address {letter} twice in one block")
                vals[letter] = v
                raw[letter] = text
        return self.motion(gs, ms, vals, raw)

    def dwell_seconds(self, vals: dict[str, float], raw: dict[str, str]) -> float:
        if "X" in vals:
            return vals["X"]
        if "P" in vals:  # P without a decimal point counts milliseconds
            return vals["P"] if "." in raw["P"] else vals["P"] / 1000.0
        raise Alarm("G04 needs P or X")

    def motion(self, gs: list[float], ms: list[int], vals: dict[str, float],
               raw: dict[str, str]) -> Flow:
        probe = dwell = home = False
        for g in gs:
            if self.modal_g(g, inch=(20.0,), metric=(21.0,)):
                pass
            elif g == 4.0:
                dwell = True
            elif g == self.probe_g:
                probe = True
            elif g == 28.0:
                home = True
            elif g == 10.0:
                if vals.get("L") != 52.0:
                    raise Alarm("G10 is supported as G10 L52 (parameter input) only")
                self.parameter_input = True
                return NEXT
            elif g in (11.0, 53.0) or g in _MODAL_NOOP:  # G11 outside L52 mode: nothing
                pass
            else:
                raise Alarm(f"G{g:g} is not supported by this controller model")
        if "F" in vals:
            if vals["F"] <= 0:
                raise Alarm("feed rate must be positive")
            self.modal.feed_mm_min = vals["F"] * (25.4 if self.modal.inch else 1.0)
        for m in ms:
            if m in (98, 99):
                raise Alarm(f"M{m} subprograms are not supported by the simulator")
        if dwell:
            self.io.dwell(self.dwell_seconds(vals, raw))
        else:
            axes = self.axis_words(vals)
            if home:
                self.reference_return(axes)
            elif probe:
                self.probe_move(axes)
            elif axes:
                self.straight_move(axes)
        for m in ms:
            if m in (2, 30):
                return END
            if m == 0:
                return Flow("stop")
            if m == 6:
                self.io.dwell(5.0)  # tool change (probe pick-up)
        return NEXT

    def reference_return(self, axes: dict[str, float]) -> None:
        """G28: through the intermediate point to the reference point (top of Z travel, X/Y
        and rotary zero)."""
        self.io.move(self.target(axes), None)
        ref = dict(self.io.position())
        for a in axes:
            ref[a] = self.io.reference(a) if hasattr(self.io, "reference") else 0.0
        self.io.move(ref, None)

    def probe_move(self, axes: dict[str, float]) -> None:
        if self.modal.feed_mm_min <= 0:
            raise Alarm(f"G{self.probe_g:g} without a feed rate (F)")
        if any(a not in "XYZ" for a in axes):
            raise Alarm(f"G{self.probe_g:g}: only X, Y, Z may move during probing")
        out = self.io.probe(self.target(axes), self.modal.feed_mm_min, locate=self.locating())
        self.store_probe(out.latched, out.triggered)

    def locating(self) -> bool:
        """Is this probing move the fast approach of a two-speed touch? (Fanuc: never — G31
        is its one probing move.)"""
        return False

    def store_probe(self, latched: dict[str, float], triggered: bool) -> None:
        for k, a in enumerate(self.io.axes):
            self.variables[f"#{5061 + k}"] = latched[a]

