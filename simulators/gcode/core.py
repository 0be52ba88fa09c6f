"""The shared interpreter core: machine interface, modal motion state, control flow, block runner.

A dialect (fanuc, linuxcnc, siemens, heidenhain) turns one block into calls on a ``MachineIO``
(moves, probing, dwell, output lines) and returns a ``Flow``; structured control flow
(IF/ELSE/ENDIF, WHILE/ENDWHILE in each language's spelling) is resolved here by seeking the
matching block, so it also works on a drip-fed program whose later blocks have not arrived yet.
"""

from __future__ import annotations

import asyncio
import re
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Protocol

from simulators.gcode.expr import ExprError, evaluate, number


class Alarm(Exception):
    """The controller stops with an alarm (program error, #3000, SETAL, FN 14, probe miss …)."""


@dataclass
class ProbeOutcome:
    """What a probing move did: latched controller values (end point on a miss)."""

    triggered: bool
    latched: dict[str, float]


class MachineIO(Protocol):
    """What a dialect may ask of the machine (implemented by the virtual controller)."""

    axes: tuple[str, ...]  # controller axis letters: X Y Z then the two rotary letters

    def position(self) -> dict[str, float]: ...
    def move(self, target: dict[str, float], feed_mm_min: float | None) -> None: ...
    def probe(self, target: dict[str, float], feed_mm_min: float, locate: bool = False
              ) -> ProbeOutcome:
        """A probing move; ``locate``: the fast approach of a two-speed touch (it finds the
        surface for the re-touch: no touch result of its own)."""
        ...
    def dwell(self, seconds: float) -> None: ...
    def output(self, text: str, target: str | None = None) -> None: ...
    def message(self, text: str) -> None: ...


@dataclass
class Flow:
    """Where execution goes after a block."""

    kind: str = "next"  # next | end | goto | jump | stop
    label: str | None = None  # goto: a label as returned by ``label_of``
    backward_first: bool = False
    index: int | None = None  # jump


NEXT = Flow()
END = Flow("end")


@dataclass
class Modal:
    motion: str = "G0"  # G0 | G1
    absolute: bool = True
    feed_mm_min: float = 0.0
    inch: bool = False


@dataclass
class Interpreter:
    """Base of the dialect interpreters: variables, modal state, word-address motion."""

    io: MachineIO
    variables: dict[str, float | str] = field(default_factory=dict)
    modal: Modal = field(default_factory=Modal)
    name: str = ""

    # ----------------------------------------------------------- dialect hooks
    def label_of(self, block: str) -> str | None:
        return None

    def structure(self, block: str) -> tuple[str, str] | None:
        """(role, key) for if/elseif/else/endif/while/endwhile blocks, else None."""
        return None

    def condition(self, block: str) -> bool:
        raise Alarm(f"no condition in {block!r}")

    def execute(self, block: str, index: int) -> Flow:
        raise NotImplementedError

    # ---------------------------------------------------------------- helpers
    def lookup(self, name: str) -> float | str:
        return self.variables.get(name, 0.0)

    def eval(self, text: str) -> float | str:
        try:
            return evaluate(text, self.lookup)
        except (ExprError, ValueError, OverflowError, ZeroDivisionError) as e:
            raise Alarm(f"bad expression {text.strip()!r}: {e}") from None

    def num(self, text: str) -> float:
        try:
            return number(text, self.lookup)
        except (ExprError, ValueError, OverflowError, ZeroDivisionError) as e:
            raise Alarm(f"bad expression {text.strip()!r}: {e}") from None

    def target(self, words: dict[str, float]) -> dict[str, float]:
        """Absolute controller target from axis words (modal G90/G91, G20 inch)."""
        pos = self.io.position()
        out = dict(pos)
        for a in self.io.axes:
            if a in words:
                v = words[a] * (25.4 if self.modal.inch and a in "XYZ" else 1.0)
                out[a] = v if self.modal.absolute else pos[a] + v
        return out

    def modal_g(self, g: float, inch: tuple[float, ...], metric: tuple[float, ...]) -> bool:
        """Apply a motion (G0/G1), distance (G90/G91) or unit code to the modal state; the unit
        codes differ by controller (Fanuc G20/G21, Siemens G70/G71). False: not one of them."""
        if g in (0.0, 1.0):
            self.modal.motion = f"G{int(g)}"
        elif g in (90.0, 91.0):
            self.modal.absolute = g == 90.0
        elif g in inch or g in metric:
            self.modal.inch = g in inch
        else:
            return False
        return True

    def straight_move(self, axes: dict[str, float]) -> None:
        """A G0 at rapid or a G1 at the modal feed to the target of these axis words."""
        feed = None
        if self.modal.motion == "G1":
            if self.modal.feed_mm_min <= 0:
                raise Alarm("G1 without a feed rate (F)")
            feed = self.modal.feed_mm_min
        self.io.move(self.target(axes), feed)

    def axis_words(self, words: dict[str, float]) -> dict[str, float]:
        bad = [w for w in words if w in "XYZABCUVW" and w not in self.io.axes]
        if bad:
            raise Alarm(f"axis {bad[0]} does not exist on this machine (axes {self.io.axes})")
        return {a: words[a] for a in self.io.axes if a in words}


# ------------------------------------------------------------------ fanuc-style word blocks

_WORD_LETTER = re.compile(r"\s*([A-Z])", re.IGNORECASE)
_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)")


def _balanced(text: str, i: int) -> int:
    depth = 0
    for j in range(i, len(text)):
        if text[j] == "[":
            depth += 1
        elif text[j] == "]":
            depth -= 1
            if depth == 0:
                return j + 1
    raise Alarm(f"unbalanced brackets in {text!r}")


def split_words(text: str) -> list[tuple[str, str]]:
    """``G01X#100Y-[#1+2]F300`` → [("G","01"), ("X","#100"), ("Y","-[#1+2]"), ("F","300")]."""
    out, i, n = [], 0, len(text)
    while i < n:
        if text[i].isspace():
            i += 1
            continue
        m = _WORD_LETTER.match(text, i)
        if not m:
            raise Alarm(f"expected an address letter at {text[i:i + 10]!r}")
        letter = m.group(1).upper()
        i = m.end()
        while i < n and text[i] == " ":
            i += 1
        j = i
        if j < n and text[j] in "+-":
            j += 1
        if j < n and text[j] == "[":
            j = _balanced(text, j)
        elif j < n and text[j] == "#":
            j += 1
            if j < n and text[j] == "[":
                j = _balanced(text, j)
            elif j < n and text[j] == "<":
                j = text.index(">", j) + 1
            else:
                while j < n and text[j].isdigit():
                    j += 1
        else:
            m2 = _NUMBER.match(text, i)
            if not m2:
                raise Alarm(f"address {letter} without a value near {text[i - 1:i + 10]!r}")
            j = m2.end()
        out.append((letter, text[i:j]))
        i = j
    return out


# ------------------------------------------------------------------------------- the runner


class BlockSource(Protocol):
    async def get(self, index: int) -> str | None:
        """Block ``index`` (waits while drip-feeding); None after the end of the stream."""
        ...


class BlockQueue:
    """The ``BlockSource`` of a controller: a whole program, or blocks drip-fed until ``close``."""

    def __init__(self) -> None:
        self.lines: list[str] = []
        self.complete = False
        self._more = asyncio.Event()

    def extend(self, lines: list[str]) -> None:
        self.lines.extend(lines)
        self._more.set()

    def close(self) -> None:
        self.complete = True
        self._more.set()

    async def get(self, index: int) -> str | None:
        while index >= len(self.lines):
            if self.complete:
                return None
            self._more.clear()
            await self._more.wait()
        return self.lines[index]


async def _seek(interp: Interpreter, source: BlockSource, start: int, key: str,
                want: tuple[str, ...], step: int) -> int:
    """Index of the next block (forward or backward) with a role in ``want`` at nesting 0."""
    opens = {"if", "while"}
    closes = {"endif", "endwhile"}
    depth, i = 0, start
    while i >= 0:
        block = await source.get(i)
        if block is None:
            break
        s = interp.structure(block)
        if s is not None:
            role, k = s
            if key:  # keyed structures (o-words, DO m): the key alone identifies the match
                if role in want and k == key:
                    return i
            else:
                if role in want and depth == 0:
                    return i
                if role in (opens if step > 0 else closes):
                    depth += 1
                elif role in (closes if step > 0 else opens):
                    depth -= 1
        i += step
    raise Alarm(f"no matching {'/'.join(want).upper()} for block {start - step + 1}")


async def _goto(interp: Interpreter, source: BlockSource, label: str, here: int,
                backward_first: bool) -> int:
    i = here if backward_first else here + 1
    if backward_first:
        while i >= 0:
            blk = await source.get(i)
            if blk is not None and interp.label_of(blk) == label:
                return i
            i -= 1
    i = 0 if not backward_first else here + 1
    while True:
        blk = await source.get(i)
        if blk is None:
            raise Alarm(f"jump target {label} not found")
        if interp.label_of(blk) == label:
            return i
        i += 1


async def run(interp: Interpreter, source: BlockSource,
              before: Callable[[int, str], Awaitable[None]],
              stop: Callable[[], Awaitable[None]] | None = None) -> None:
    """Execute blocks until the end of the program (M30, %, END PGM) or of the stream;
    ``stop`` is awaited on a program stop (M00, #3006, STOP) until cycle start."""
    pc = 0
    while True:
        block = await source.get(pc)
        if block is None:
            return
        await before(pc, block)
        s = interp.structure(block)
        if s is None:
            flow = interp.execute(block, pc)
        else:
            role, key = s
            if role in ("if", "while"):
                ok = interp.condition(block)
                if ok:
                    flow = NEXT
                elif role == "while":
                    flow = Flow("jump", index=await _seek(interp, source, pc + 1, key,
                                                          ("endwhile",), 1) + 1)
                else:
                    flow = await _after_false(interp, source, pc, key)
            elif role in ("elseif", "else"):  # reached after a taken branch: skip to ENDIF
                flow = Flow("jump", index=await _seek(interp, source, pc + 1, key,
                                                      ("endif",), 1) + 1)
            elif role == "endwhile":
                flow = Flow("jump", index=await _seek(interp, source, pc - 1, key,
                                                      ("while",), -1))
            else:  # endif
                flow = NEXT
        if flow.kind == "next":
            pc += 1
        elif flow.kind == "end":
            return
        elif flow.kind == "jump":
            pc = int(flow.index or 0)
        elif flow.kind == "goto":
            pc = await _goto(interp, source, str(flow.label), pc, flow.backward_first)
        elif flow.kind == "stop":
            if stop is not None:
                await stop()
            pc += 1
        else:
            raise Alarm(f"unknown flow {flow.kind}")


async def _after_false(interp: Interpreter, source: BlockSource, pc: int, key: str) -> Flow:
    i = pc
    while True:
        j = await _seek(interp, source, i + 1, key, ("elseif", "else", "endif"), 1)
        blk = await source.get(j)
        role = interp.structure(blk or "")
        if role and role[0] == "elseif":
            if interp.condition(blk or ""):
                return Flow("jump", index=j + 1)
            i = j
            continue
        return Flow("jump", index=j + 1)
