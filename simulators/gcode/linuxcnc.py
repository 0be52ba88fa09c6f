"""LinuxCNC (rs274ngc) dialect: O-word flow, ``#<named>`` parameters, G38.2/G38.3, (LOG,…).

Probe results as in LinuxCNC 2.9: ``#5061``-``#5069`` X Y Z A B C U V W at the trip (the end
point when nothing tripped) and ``#5070`` = 1 on success; G38.2 without contact is an error
("G38.2 move finished without making contact"), G38.3 is not. Our programs use G38.3 only as the
fast approach of a two-speed touch (G38.3, G1 back-off from #5061…, G38.2 slow): it is a
locating move, not a touch result (``MachineIO.probe(locate=True)``). ``(LOG,…)``/``(DEBUG,…)``
substitute parameters with six decimals; ``(ABORT,…)`` stops with an error.
"""

from __future__ import annotations

import re

from simulators.gcode.core import END, NEXT, Alarm, Flow
from simulators.gcode.fanuc import FanucInterpreter

_OWORD = re.compile(r"^O\s*(\d+|<[^>]+>)\s+(IF|ELSEIF|ELSE|ENDIF|WHILE|ENDWHILE|DO|BREAK|"
                    r"CONTINUE|SUB|ENDSUB|CALL|RETURN|REPEAT|ENDREPEAT)\b\s*(.*)$",
                    re.IGNORECASE)
_SPECIAL = re.compile(r"^\(\s*(LOGOPEN|LOGAPPEND|LOGCLOSE|PROBEOPEN|PROBECLOSE|MSG|LOG|DEBUG|PRINT|"
                      r"ABORT)\s*,?(.*)\)$", re.IGNORECASE)
_PARAM = re.compile(r"#(<[^>]+>|\d+)")
_ASSIGN = re.compile(r"(#\s*(?:<[^>]+>|\d+|\[[^\]]*\]))\s*=\s*")
_LETTERS = "XYZABCUVW"


def _strip(block: str) -> tuple[str, list[str]]:
    """(code, comments); ``;`` starts a comment to the end of the line."""
    comments = re.findall(r"\([^)]*\)", block)
    code = re.sub(r"\([^)]*\)", "", block)
    code = code.split(";", 1)[0].strip()
    if code.startswith("/"):
        code = code[1:].strip()
    return code, comments


class LinuxcncInterpreter(FanucInterpreter):
    probe_g = 38.2
    _log_open = False

    def __init__(self, io, variables=None, name: str = "linuxcnc") -> None:
        super().__init__(io, variables, name=name)

    def lookup(self, name: str) -> float | str:
        if name.startswith("#<"):
            key = name.lower().replace(" ", "")
            if key not in self.variables:
                raise Alarm(f"named parameter {name} not defined")
            return self.variables[key]
        n = int(name[1:])
        if 5420 <= n <= 5428:
            letter = _LETTERS[n - 5420]
            return self.io.position().get(letter, 0.0)
        return self.variables.get(name, 0.0)

    def label_of(self, block: str) -> str | None:
        return None  # LinuxCNC has no GOTO

    def structure(self, block: str) -> tuple[str, str] | None:
        code, _ = _strip(block)
        code = re.sub(r"^N\d+\s*", "", code, flags=re.IGNORECASE)
        m = _OWORD.match(code)
        if not m:
            return None
        word = m.group(2).lower()
        key = m.group(1).lower()
        if word in ("if", "elseif", "else", "endif", "while", "endwhile"):
            return (word, key)
        return None

    def condition(self, block: str) -> bool:
        code, _ = _strip(block)
        m = _OWORD.match(re.sub(r"^N\d+\s*", "", code, flags=re.IGNORECASE))
        if not m or not m.group(3).strip():
            raise Alarm(f"O-word condition missing in {block!r}")
        return bool(self.num(m.group(3)))

    def _subst(self, text: str) -> str:
        def one(m: re.Match[str]) -> str:
            ref = m.group(1)
            v = self.lookup(f"#{ref.lower()}" if ref.startswith("<") else f"#{ref}")
            return f"{float(v):.6f}"

        return _PARAM.sub(one, text)

    def execute(self, block: str, index: int) -> Flow:
        code, comments = _strip(block)
        if code == "%":
            return NEXT if index == 0 else END
        for c in comments:
            m = _SPECIAL.match(c.strip())
            if not m:
                continue
            kind, text = m.group(1).upper(), m.group(2).strip()
            if kind in ("LOG", "DEBUG", "PRINT"):
                # LOG goes to the LOGOPEN file; DEBUG/PRINT to the operator/stderr. The
                # controller reports all three as output lines (what a front-end reads back).
                self.io.output(self._subst(text))
            elif kind == "MSG":
                self.io.message(text)
            elif kind == "ABORT":
                raise Alarm(f"abort: {self._subst(text)}")
        code = re.sub(r"^N\d+\s*", "", code, flags=re.IGNORECASE)
        if not code:
            return NEXT
        m = _OWORD.match(code)
        if m:
            word = m.group(2).upper()
            raise Alarm(f"O-word {word} is not supported by the simulator")
        # Parameter settings take effect after the whole line is read (rs274ngc semantics).
        assigns = []
        parts = _ASSIGN.split(code)
        if len(parts) > 1:
            words_text = parts[0]
            for k in range(1, len(parts), 2):
                target, rest = parts[k], parts[k + 1]
                assigns.append((target, rest.strip()))
            for target, expr_text in assigns:
                if not expr_text:
                    raise Alarm(f"assignment to {target} without a value")
            values = [(t, self.num(e)) for t, e in assigns]
            flow = self.words(words_text) if words_text.strip() else NEXT
            for t, v in values:
                t = t.replace(" ", "")
                if t.startswith("#<"):
                    self.variables[t.lower()] = v
                elif t.startswith("#["):
                    self.variables[f"#{round(self.num(t[2:-1]))}"] = v
                else:
                    n = int(t[1:])
                    if not 1 <= n <= 5399 or 5061 <= n <= 5070:
                        raise Alarm(f"parameter #{n} is read-only")
                    self.variables[f"#{n}"] = v
            return flow
        return self.words(code)

    def dwell_seconds(self, vals: dict[str, float], raw: dict[str, str]) -> float:
        if "P" not in vals:
            raise Alarm("G4 needs P (seconds)")
        return vals["P"]

    def motion(self, gs, ms, vals, raw) -> Flow:
        for g in gs:
            if g in (38.4, 38.5):
                raise Alarm(f"G{g:g} (probe away) is not used by our programs")
        self.probe_g = 38.3 if 38.3 in gs else 38.2
        return super().motion(gs, ms, vals, raw)

    def locating(self) -> bool:
        return self.probe_g == 38.3

    def store_probe(self, latched: dict[str, float], triggered: bool) -> None:
        for letter in _LETTERS:
            if letter in latched:
                self.variables[f"#{5061 + _LETTERS.index(letter)}"] = latched[letter]
        self.variables["#5070"] = 1.0 if triggered else 0.0
        if not triggered and self.probe_g == 38.2:
            raise Alarm("G38.2 move finished without making contact")
