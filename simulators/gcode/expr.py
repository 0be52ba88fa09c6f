"""Expressions of the four controller languages: one recursive-descent evaluator, dialect lookups.

Covers what our programs emit and the usual controller forms: Fanuc/Haas macro B and LinuxCNC
(``#100``, ``#[#1+2]``, ``#<name>``, ``[ ]`` grouping, ``SIN[…]``, ``EQ NE GT GE LT LE AND OR
XOR MOD``, ``ATAN[a]/[b]``), Siemens (``R10``, ``R[…]``, ``$AA_MM[X]``, ``( )``, ``== <> >= <=``,
strings with ``<<``, ``SPRINT``) and Heidenhain Q parameters (``Q115``, ``QL1``, ``QR1``).
Trigonometry is in degrees on every controller.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable

_TOKEN = re.compile(
    r"""\s*(?:
      (?P<num>(?:\d+\.?\d*|\.\d+)(?:E[-+]?\d+)?)
    | (?P<str>"[^"]*"|'[^']*')
    | (?P<var>\#<[^>]+>|\#\d+|\$[A-Z_][A-Z0-9_]*(?:\[[^\]]*\])?|(?:QL|QR|QS|Q|R)\d+)
    | (?P<op>\*\*|==|<>|>=|<=|<<|[-+*/<>\[\](),=\#])
    | (?P<word>(?:EQU|EQ|NE|GT|GE|LT|LE|AND|OR|XOR|MOD)(?=[\d.\#\[(+-]))
    | (?P<name>[A-Z_][A-Z0-9_]*)
    )""",
    re.VERBOSE | re.IGNORECASE,
)

_CMP_WORDS = {"EQ": "==", "NE": "<>", "GT": ">", "GE": ">=", "LT": "<", "LE": "<=",
              "EQU": "==", "NEQ": "<>"}
_CMP = {"==": lambda a, b: a == b, "<>": lambda a, b: a != b, ">": lambda a, b: a > b,
        ">=": lambda a, b: a >= b, "<": lambda a, b: a < b, "<=": lambda a, b: a <= b}


def _fix(x: float) -> float:
    return float(math.floor(x))


_FUNCS: dict[str, Callable[..., float]] = {
    "SIN": lambda x: math.sin(math.radians(x)),
    "COS": lambda x: math.cos(math.radians(x)),
    "TAN": lambda x: math.tan(math.radians(x)),
    "ASIN": lambda x: math.degrees(math.asin(x)),
    "ACOS": lambda x: math.degrees(math.acos(x)),
    "ATAN": lambda x: math.degrees(math.atan(x)),
    "ATAN2": lambda y, x: math.degrees(math.atan2(y, x)),
    "SQRT": math.sqrt, "SQ": lambda x: x * x, "POT": lambda x: x * x,
    "ABS": abs, "SGN": lambda x: float((x > 0) - (x < 0)), "LN": math.log, "EXP": math.exp,
    "ROUND": lambda x: float(math.floor(x + 0.5)) if x >= 0 else -float(math.floor(-x + 0.5)),
    "FIX": _fix, "FUP": lambda x: float(math.ceil(x)),
    "TRUNC": lambda x: float(math.trunc(x)), "INT": lambda x: float(math.trunc(x)),
    "MIN": min, "MAX": max,
}


class ExprError(ValueError):
    """A malformed expression; the message says where."""


Lookup = Callable[[str], float | str]


def tokenize(text: str) -> list[tuple[str, str]]:
    out, pos = [], 0
    text = text.rstrip()
    while pos < len(text):
        m = _TOKEN.match(text, pos)
        if not m or m.end() == pos:
            raise ExprError(f"unexpected {text[pos:pos + 12]!r}")
        kind = m.lastgroup or ""
        val = m.group(kind)
        if kind == "word":  # Fanuc writes #1LT0.001: an operator glued to a number
            kind = "name"
        if kind in ("name", "var"):
            val = val.upper() if not val.startswith("#<") else val.lower()
        out.append((kind, val))
        pos = m.end()
    return out


class Parser:
    """Evaluates one expression from a token list; ``lookup`` resolves variable names."""

    def __init__(self, tokens: list[tuple[str, str]], lookup: Lookup) -> None:
        self.t = tokens
        self.i = 0
        self.lookup = lookup

    # helpers
    def peek(self, k: int = 0) -> tuple[str, str]:
        j = self.i + k
        return self.t[j] if j < len(self.t) else ("end", "")

    def take(self) -> tuple[str, str]:
        tok = self.peek()
        self.i += 1
        return tok

    def expect(self, val: str) -> None:
        tok = self.take()
        if tok[1] != val:
            raise ExprError(f"expected {val!r}, got {tok[1] or 'end of block'!r}")

    @property
    def done(self) -> bool:
        return self.i >= len(self.t)

    # grammar (lowest precedence first)
    def expr(self) -> float | str:
        v = self.and_()
        while self.peek()[1] in ("OR", "XOR"):
            op = self.take()[1]
            r = self.and_()
            v = float(bool(v) or bool(r)) if op == "OR" else float(bool(v) != bool(r))
        return v

    def and_(self) -> float | str:
        v = self.not_()
        while self.peek()[1] == "AND":
            self.take()
            r = self.not_()
            v = float(bool(v) and bool(r))
        return v

    def not_(self) -> float | str:
        if self.peek()[1] == "NOT":
            self.take()
            return float(not self.not_())
        return self.cmp()

    def cmp(self) -> float | str:
        v = self.concat()
        op = self.peek()[1]
        op = _CMP_WORDS.get(op, op)
        if op in _CMP:
            self.take()
            r = self.concat()
            if isinstance(v, float) and isinstance(r, float):
                return float(_CMP[op](v, r))
            return float(_CMP[op](str(v), str(r)))
        return v

    def concat(self) -> float | str:
        v = self.add()
        while self.peek()[1] == "<<":
            self.take()
            v = _to_str(v) + _to_str(self.add())
        return v

    def add(self) -> float | str:
        v = self.mul()
        while self.peek()[1] in ("+", "-"):
            op = self.take()[1]
            r = self.mul()
            v = _num(v) + _num(r) if op == "+" else _num(v) - _num(r)
        return v

    def mul(self) -> float | str:
        v = self.power()
        while self.peek()[1] in ("*", "/", "MOD", "DIV"):
            op = self.take()[1]
            r = _num(self.power())
            if op == "*":
                v = _num(v) * r
            elif r == 0:
                raise ExprError("division by zero")
            elif op == "/":
                v = _num(v) / r
            elif op == "MOD":
                v = math.fmod(_num(v), r)
            else:
                v = float(int(_num(v) / r))
        return v

    def power(self) -> float | str:
        v = self.unary()
        if self.peek()[1] == "**":
            self.take()
            return _num(v) ** _num(self.power())
        return v

    def unary(self) -> float | str:
        if self.peek()[1] == "-":
            self.take()
            return -_num(self.unary())
        if self.peek()[1] == "+":
            self.take()
            return _num(self.unary())
        return self.atom()

    def group(self) -> float | str:
        open_ = self.take()[1]
        v = self.expr()
        self.expect("]" if open_ == "[" else ")")
        return v

    def atom(self) -> float | str:
        kind, val = self.peek()
        if kind == "num":
            self.take()
            return float(val)
        if kind == "str":
            self.take()
            return val[1:-1]
        if val in ("[", "("):
            return self.group()
        if kind == "var":
            self.take()
            if val.startswith("$") and "[" in val:
                return self.lookup(_system_var(val, self.lookup))
            return self.lookup(val)
        if val == "#":  # #[expr] or ##1
            self.take()
            idx = self.group() if self.peek()[1] == "[" else self.atom()
            return self.lookup(f"#{round(_num(idx))}")
        if kind == "name":
            self.take()
            if val == "R" and self.peek()[1] == "[":
                return self.lookup(f"R{round(_num(self.group()))}")
            if val == "SPRINT":
                return self.sprint()
            if val in _FUNCS:
                if val == "ATAN" and self.peek()[1] == "[":
                    y = _num(self.group())
                    if self.peek()[1] == "/" and self.peek(1)[1] == "[":  # ATAN[a]/[b]
                        self.take()
                        x = _num(self.group())
                        return math.degrees(math.atan2(y, x))
                    return math.degrees(math.atan(y))
                if self.peek()[1] in ("[", "("):
                    close = "]" if self.take()[1] == "[" else ")"
                    args = [_num(self.expr())]
                    while self.peek()[1] == ",":
                        self.take()
                        args.append(_num(self.expr()))
                    self.expect(close)
                    return float(_FUNCS[val](*args))
                return float(_FUNCS[val](_num(self.unary())))  # Heidenhain: SIN Q1
            return self.lookup(val)
        raise ExprError(f"unexpected {val or 'end of block'!r}")

    def sprint(self) -> str:
        self.expect("(")
        fmt = self.expr()
        args = []
        while self.peek()[1] == ",":
            self.take()
            args.append(self.expr())
        self.expect(")")
        return _sprint(str(fmt), args)


def _system_var(val: str, lookup: Lookup) -> str:
    """``$AA_MM[X]`` stays by name; ``$AC_MEA[R1]`` gets its numeric index evaluated."""
    name, idx = val[:-1].split("[", 1)
    idx = idx.strip().upper()
    if re.fullmatch(r"[XYZABC]", idx) or re.fullmatch(r"\d+", idx):
        return f"{name}[{idx}]"
    return f"{name}[{round(_num(evaluate(idx, lookup)))}]"


def _num(v: float | str) -> float:
    if isinstance(v, str):
        raise ExprError(f"expected a number, got the string {v!r}")
    return float(v)


def _to_str(v: float | str) -> str:
    if isinstance(v, str):
        return v
    # Siemens converts a REAL in a string chain with up to 10 significant digits.
    return f"{v:.10g}"


def _sprint(fmt: str, args: list[float | str]) -> str:
    out, k = [], 0
    for m in re.finditer(r"%(-?\d*(?:\.\d+)?)([FDSE])|[^%]+|%", fmt, re.IGNORECASE):
        if m.group(2):
            spec, conv = m.group(1), m.group(2).upper()
            if k >= len(args):
                raise ExprError(f"SPRINT: too few arguments for {fmt!r}")
            a = args[k]
            k += 1
            out.append(format(a if conv == "S" else (round(_num(a)) if conv == "D"
                                                       else _num(a)),
                              spec + {"F": "f", "D": "d", "S": "s", "E": "e"}[conv]))
        else:
            out.append(m.group(0))
    return "".join(out)


def evaluate(text: str | list[tuple[str, str]], lookup: Lookup) -> float | str:
    """Evaluate a whole expression (a string or tokens)."""
    toks = tokenize(text) if isinstance(text, str) else text
    p = Parser(toks, lookup)
    v = p.expr()
    if not p.done:
        raise ExprError(f"unexpected {p.peek()[1]!r} after the expression")
    return v


def number(text: str, lookup: Lookup) -> float:
    """Evaluate an expression that must give a number."""
    return _num(evaluate(text, lookup))
