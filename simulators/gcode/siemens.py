"""Siemens Sinumerik 840D dialect: R parameters, DEF, MEAS=1 measuring moves, $AA_MM / $AA_MW /
$AC_MEA, WRITE, MSG, SETAL, IF/ELSE/ENDIF, WHILE/ENDWHILE, GOTOF/GOTOB, labels.

A measuring move that does not trigger ends at its end point with ``$AC_MEA[1] = 0`` and no
alarm (the part program decides). Comments start with ``;``.

Tool-carrier data ``$TC_CARR<n>[<k>] = <expr>`` writes the control's kinematic value
(``io.kinematics``, simulators/controller_kinematics.py; never the truth) and ``$TC_CARR<n>[<k>]``
reads it back in expressions; only the values the Siemens section declares exist here, any other
raises an alarm (refused rather than silently kept).
"""

from __future__ import annotations

import re
from typing import TYPE_CHECKING

from contracts.dialects import dialect
from simulators.gcode.core import END, NEXT, Alarm, Flow, Interpreter

if TYPE_CHECKING:
    from simulators.controller_kinematics import KinematicsStore

_N = re.compile(r"^\s*N\d+\s*", re.IGNORECASE)
_LABEL = re.compile(r"^([A-Z_][A-Z0-9_]{1,31}):\s*", re.IGNORECASE)
_DEF = re.compile(r"^DEF\s+(REAL|INT|BOOL|STRING\s*\[\s*\d+\s*\]|CHAR|AXIS|FRAME)\s+(.+)$",
                  re.IGNORECASE)
_ASSIGN = re.compile(r"^(R\d+|R\[[^\]]+\]|[A-Z_][A-Z0-9_]*)\s*=\s*(.+)$", re.IGNORECASE)
_CARR = re.compile(r"^(\$TC_CARR\d+\[\s*\d+\s*\])\s*=\s*(.+)$", re.IGNORECASE)
_IF = re.compile(r"^IF\s*(.+?)\s+(GOTOF|GOTOB|GOTO|GOTOC)\s+(\w+)$", re.IGNORECASE)
_CALL = re.compile(r"^(WRITE|MSG|SETAL)\s*\((.*)\)$", re.IGNORECASE)
_ADDRESS_WORD = re.compile(r"\s*([A-Z]+)\s*(=\s*(?:\([^;]*?\)|\"[^\"]*\"|[^\s]+)|"
                           r"[-+]?(?:\d+\.?\d*|\.\d+))", re.IGNORECASE)
_SKIP_WORDS = {"STOPRE", "SUPA", "TRAFOOF", "RTLION", "CFC", "FFWOF", "SOFT", "BRISK", "G601",
               "G602"}
_MODAL_NOOP = {17.0, 40.0, 60.0, 64.0, 94.0, 500.0, 53.0, 153.0, 54.0, 55.0, 56.0, 57.0}
_DIRECT_ADDR = set("GMFNXYZABCSTDHR")


def _strip(block: str) -> str:
    code = block.split(";", 1)[0].strip()
    return code[1:].strip() if code.startswith("/") else code


class SiemensInterpreter(Interpreter):
    def __init__(self, io, variables=None, name: str = "siemens") -> None:
        super().__init__(io, variables if variables is not None else {}, name=name)
        self.meas: dict[str, float] = {}
        self.meas_ok = 0.0

    def _code(self, block: str) -> str:
        code = _N.sub("", _strip(block), count=1)
        return _LABEL.sub("", code, count=1).strip()

    def lookup(self, name: str) -> float | str:
        if name.startswith("$"):
            base, _, idx = name[:-1].partition("[")
            if base in ("$AA_MM", "$AA_MW"):
                if idx not in self.meas:
                    raise Alarm(f"{name}: no measurement of axis {idx} yet")
                return self.meas[idx]
            if base in ("$AA_IW", "$AA_IM"):
                pos = self.io.position()
                if idx not in pos:
                    raise Alarm(f"{name}: no axis {idx}")
                return pos[idx]
            if base == "$AC_MEA":
                return self.meas_ok
            if base.startswith("$TC_CARR"):
                return self._carrier(name).read(name)
            raise Alarm(f"system variable {name} is not simulated")
        if name.startswith("R"):
            return self.variables.get(name, 0.0)
        if name not in self.variables:
            raise Alarm(f"variable {name} not defined (DEF missing)")
        return self.variables[name]

    def _carrier(self, address: str) -> KinematicsStore:
        """The kinematic store holding ``address`` (a declared tool-carrier value)."""
        store = getattr(self.io, "kinematics", None)
        if store is None or not dialect(store.family).carrier or not store.holds(address):
            raise Alarm(f"{address}: not a tool-carrier value of this control")
        return store

    def label_of(self, block: str) -> str | None:
        code = _N.sub("", _strip(block), count=1)
        m = _LABEL.match(code)
        if m:
            return m.group(1).upper()
        m = re.match(r"^\s*N(\d+)", _strip(block), re.IGNORECASE)
        return f"N{int(m.group(1))}" if m else None

    def structure(self, block: str) -> tuple[str, str] | None:
        code = self._code(block).upper()
        if code.startswith("IF") and not _IF.match(self._code(block)):
            return ("if", "")
        for word, role in (("ELSE", "else"), ("ENDIF", "endif"), ("ENDWHILE", "endwhile")):
            if code == word:
                return (role, "")
        if re.match(r"^WHILE\b", code):
            return ("while", "")
        return None

    def condition(self, block: str) -> bool:
        code = self._code(block)
        return bool(self.num(re.sub(r"^(IF|WHILE)\s*", "", code, flags=re.IGNORECASE)))

    def execute(self, block: str, index: int) -> Flow:
        code = self._code(block)
        if not code:
            return NEXT
        up = code.upper()
        m = _DEF.match(code)
        if m:
            kind = m.group(1).upper()
            for part in m.group(2).split(","):
                name, _, init = part.partition("=")
                name = name.strip().upper()
                value = self.eval(init) if init.strip() else ("" if kind.startswith("STRING")
                                                             else 0.0)
                self.variables[name] = value
            return NEXT
        m = _CARR.match(code)
        if m:
            address = m.group(1).replace(" ", "").upper()
            self._carrier(address).write(address, self.num(m.group(2)), "$TC_CARR=")
            return NEXT
        m = _IF.match(code)
        if m:
            if self.num(m.group(1)):
                return self._goto(m.group(2).upper(), m.group(3).upper())
            return NEXT
        m = re.match(r"^(GOTOF|GOTOB|GOTO)\s+(\w+)$", code, re.IGNORECASE)
        if m:
            return self._goto(m.group(1).upper(), m.group(2).upper())
        m = _CALL.match(code)
        if m:
            return self._call(m.group(1).upper(), m.group(2))
        m = _ASSIGN.match(code)
        if m and m.group(1).upper() not in _DIRECT_ADDR | {"MEAS", "MEAW"}:
            target = m.group(1).upper()
            value = self.eval(m.group(2))
            if target.startswith("R["):
                target = f"R{round(self.num(target[2:-1]))}"
            elif (not target.startswith("R") or not target[1:].isdigit()) and \
                    target not in self.variables:
                raise Alarm(f"variable {target} not defined (DEF missing)")
            self.variables[target] = value
            return NEXT
        if up in _SKIP_WORDS:
            return NEXT
        return self._words(code)

    def _goto(self, kind: str, label: str) -> Flow:
        return Flow("goto", label=label, backward_first=(kind == "GOTOB"))

    def _call(self, name: str, args: str) -> Flow:
        parts = _split_args(args)
        if name == "WRITE":
            if len(parts) != 3:
                raise Alarm("WRITE needs (error variable, file, string)")
            text = self.eval(parts[2])
            self.io.output(str(text))
            err = parts[0].strip().upper()
            if err in self.variables or err.startswith("R"):
                self.variables[err] = 0.0
            return NEXT
        if name == "MSG":
            self.io.message(str(self.eval(parts[0])) if parts and parts[0].strip() else "")
            return NEXT
        raise Alarm(f"SETAL {int(self.num(parts[0]))}" + (f" {self.eval(parts[1])}"
                                                          if len(parts) > 1 else ""))

    def _words(self, code: str) -> Flow:
        pos, gs, ms, vals, meas = 0, [], [], {}, None
        while pos < len(code):
            m = _ADDRESS_WORD.match(code, pos)
            if not m:
                if code[pos:].strip() == "":
                    break
                raise Alarm(f"cannot read {code[pos:pos + 12]!r}")
            addr, val = m.group(1).upper(), m.group(2)
            pos = m.end()
            v = self.num(val.lstrip("=")) if val.startswith("=") else float(val)
            if addr == "G":
                gs.append(round(v, 1))
            elif addr == "M":
                ms.append(int(v))
            elif addr == "MEAS":
                meas = int(v)
            elif addr in _SKIP_WORDS:
                continue
            elif len(addr) == 1:
                vals[addr] = v
            else:
                raise Alarm(f"address {addr} is not supported by the simulator")
        dwell = False
        for g in gs:
            if self.modal_g(g, inch=(70.0, 700.0), metric=(71.0, 710.0)):
                pass
            elif g == 4.0:
                dwell = True
            elif g not in _MODAL_NOOP:
                raise Alarm(f"G{g:g} is not supported by this controller model")
        if dwell:
            if "F" not in vals and "S" not in vals:
                raise Alarm("G4 needs F (seconds)")
            self.io.dwell(vals.get("F", 0.0))
            vals.pop("F", None)
        elif "F" in vals:
            if vals["F"] <= 0:
                raise Alarm("feed rate must be positive")
            self.modal.feed_mm_min = vals["F"]
        axes = self.axis_words({k: v for k, v in vals.items() if k in "XYZABCUVW"})
        if meas is not None:
            if meas != 1:
                raise Alarm(f"MEAS={meas}: only probe 1 rising edge is used")
            if self.modal.motion != "G1" or self.modal.feed_mm_min <= 0:
                raise Alarm("MEAS needs G1 with a feed rate")
            out = self.io.probe(self.target(axes), self.modal.feed_mm_min)
            self.meas = dict(out.latched)
            self.meas_ok = 1.0 if out.triggered else 0.0
        elif axes and not dwell:
            self.straight_move(axes)
        for mc in ms:
            if mc in (2, 17, 30):
                return END
            if mc == 0:
                return Flow("stop")
        return NEXT


def _split_args(text: str) -> list[str]:
    """Split call arguments on top-level commas (not inside strings or parentheses)."""
    out, depth, cur, quote = [], 0, [], False
    for ch in text:
        if ch == '"':
            quote = not quote
        elif not quote and ch in "([":
            depth += 1
        elif not quote and ch in ")]":
            depth -= 1
        if ch == "," and depth == 0 and not quote:
            out.append("".join(cur))
            cur = []
        else:
            cur.append(ch)
    out.append("".join(cur))
    return [p.strip() for p in out]
