"""LinuxCNC program text for the link (drivers/linuxcnc/link.py): MDI steps, the AUTO program file,
and naming the block and touch an error belongs to."""

from __future__ import annotations

import re
from dataclasses import dataclass

from drivers.base import LinkError

_ASSIGN = re.compile(r"^#\d+\s*=\s*(?:[-+]?[0-9.]+|#\d+)$")
_LOG = re.compile(r"^\(LOG,(RUMBA .*)\)$", re.IGNORECASE)
_LOGFILE = re.compile(r"^\(LOG(OPEN|APPEND|CLOSE)?\b.*\)$", re.IGNORECASE)
_SKIP = re.compile(r"^(%|\(.*\)|o\d+\s+(if|endif|else)\b.*|M0*2|M30)$", re.IGNORECASE)
_MAX_LINE = 240  # RS274NGC lines are < 256 characters


@dataclass(frozen=True)
class Step:
    """One thing to do for a program line: an MDI block, or read a result."""

    kind: str  # "mdi" | "result"
    text: str
    line: int  # 1-based program line
    touch: str = ""  # identity of the touch a probing block belongs to (for messages)
    prefix: str = ""  # result steps: parameter settings sent on the same MDI line


def plan_steps(text: str) -> list[Step]:
    """Turn the linuxcnc-dialect program into MDI steps (rules: the docstring of link.py)."""
    lines = text.replace("\r\n", "\n").split("\n")
    steps: list[Step] = []
    pending: list[tuple[int, str]] = []

    def flush() -> None:
        while pending:
            first, merged = pending[0][0], pending[0][1]
            del pending[0]
            while pending and len(merged) + 1 + len(pending[0][1]) <= _MAX_LINE:
                merged += " " + pending.pop(0)[1]
            steps.append(Step("mdi", merged, first))

    for n, raw in enumerate(lines, 1):
        s = raw.strip()
        if not s:
            continue
        if len(s) > _MAX_LINE or not s.isascii() or "\x00" in s:
            raise LinkError(f"program line {n}: not a LinuxCNC MDI line (ASCII, < {_MAX_LINE})")
        m = _LOG.fullmatch(s)
        if m:
            # the last settings ride on the result's MDI line (one block less per touch);
            # LinuxCNC substitutes the message's parameters before the line's settings apply
            prefix: list[str] = []
            while pending and len(" ".join([pending[-1][1], *prefix])) + len(s) < _MAX_LINE:
                prefix.insert(0, pending.pop()[1])
            flush()
            steps.append(Step("result", m.group(1), n, prefix=" ".join(prefix)))
            continue
        if _SKIP.fullmatch(s):
            continue
        if _ASSIGN.fullmatch(s):
            pending.append((n, re.sub(r"\s*=\s*", "=", s)))
            continue
        flush()
        steps.append(Step("mdi", s, n))
    flush()
    # name each probing block by the identity of the result line that follows it
    ident = ""
    for i in range(len(steps) - 1, -1, -1):
        st = steps[i]
        if st.kind == "result":
            f = st.text.split()
            ident = f"touch seq {f[1]} pose {f[3]} ball {f[4]} touch {f[5]}" if len(f) > 5 else ""
        elif "G38" in st.text.upper():
            steps[i] = Step(st.kind, st.text, st.line, ident)
    return steps


def auto_program(text: str) -> str:
    """The program file for an AUTO run: the job's text line for line (LinuxCNC's line numbers
    are the program's), each ``(LOG,RUMBA …)`` as ``(DEBUG,RUMBA …)`` (the result comes back
    through the message channel, parameters substituted once the G38.2 before it finished: a
    probe move makes the interpreter wait for the motion queue) and the other ``(LOG…)``
    comments (LOGOPEN, LOGCLOSE) neutralised: no log file on the LinuxCNC PC."""
    out = []
    for n, raw in enumerate(text.replace("\r\n", "\n").split("\n"), 1):
        s = raw.strip()
        if len(s) > _MAX_LINE or not s.isascii() or "\x00" in s:
            raise LinkError(f"program line {n}: not a LinuxCNC line (ASCII, < {_MAX_LINE})")
        m = _LOG.fullmatch(s)
        if m:
            s = f"(DEBUG,{m.group(1)})"
        elif _LOGFILE.fullmatch(s):
            s = "(rumba: results through DEBUG)"
        out.append(s)
    return "\n".join(out).rstrip("\n") + "\n"


def where(step: Step) -> str:
    """The program line and text of a block, with its touch."""
    at = f"program line {step.line} '{step.text}'" if step.line else f"'{step.text}'"
    return at + (f" ({step.touch})" if step.touch else "")


def name_error(errs: list[str], n: int, probes: list[Step], lines: list[str]) -> str:
    """An AUTO run's LinuxCNC messages (``<line> text`` each) with where it stopped: the
    probing block of that line, for a probe error the touch after the ``n`` results read, or
    else the program line."""
    first_line, _, _ = errs[0].partition(" ")
    text = "; ".join(e.partition(" ")[2] for e in errs)
    line = int(first_line) if first_line.isdigit() else 0
    step = next((st for st in probes if st.line == line), None)
    if step is None and ("G38" in text or "probe" in text.lower()) and n < len(probes):
        step = probes[n]
    if step is not None:
        return f"{text} at {where(step)}"
    if 0 < line <= len(lines):
        return f"{text} at program line {line} '{lines[line - 1].strip()}' (after touch {n})"
    return f"{text} after touch {n}"
