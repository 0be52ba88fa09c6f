"""Shared fuzz machinery: outcome tally, per-case time limit, seeded random palettes."""

from __future__ import annotations

import contextlib
import random
import re
import signal
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config"
BAD = ("traceback", "hang", "wrong", "refusal")  # wrong: acceptance; refusal: of a valid input
KEEP = 3  # reproducers kept per bad class
KIND = re.compile(r"(?:['\"].*|\d+|=.*|offset.*)")
EXC_NAME = re.compile(r"Traceback|\b[A-Z]\w*(?:Error|Exception)\b")


class Hang(BaseException):
    """Raised by the per-case alarm (a BaseException so ``except Exception`` cannot eat it)."""


@contextlib.contextmanager
def time_limit(seconds: float) -> Iterator[None]:
    """Interrupt the main thread with ``Hang`` after ``seconds`` (pure-Python code only)."""
    def _raise(_sig: int, _frame: object) -> None:
        raise Hang(f"over {seconds:g} s")
    old = signal.signal(signal.SIGALRM, _raise)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


@dataclass
class Tally:
    """Outcome counts of one target and the first ``KEEP`` reproducers of each bad class."""

    target: str
    tried: int = 0
    accepted: int = 0
    clean: int = 0
    bad: dict[str, int] = field(default_factory=lambda: dict.fromkeys(BAD, 0))
    cases: dict[str, list[str]] = field(default_factory=lambda: {k: [] for k in BAD})
    notes: dict[str, int] = field(default_factory=dict)
    kinds: dict[str, str] = field(default_factory=dict)  # first reproducer of each distinct kind
    seconds: float = 0.0

    def add(self, outcome: str, repro: str = "", detail: str = "") -> None:
        self.tried += 1
        if outcome == "accepted":
            self.accepted += 1
        elif outcome == "clean":
            self.clean += 1
        else:
            self.bad[outcome] += 1
            if len(self.cases[outcome]) < KEEP:
                self.cases[outcome].append(repro[:600])
            kind = f"{outcome}: {KIND.sub('', detail)[:70]}"
            if kind not in self.kinds and len(self.kinds) < 20:
                self.kinds[kind] = repro[:600]

    def note(self, name: str) -> None:
        self.notes[name] = self.notes.get(name, 0) + 1


def run_case(tally: Tally, limit_s: float, case: Callable[[], tuple[str, str]],
             describe: Callable[[], str]) -> None:
    """Run one case: ``case`` returns (outcome, detail); escapes are tracebacks, alarms hangs."""
    t0 = time.perf_counter()
    try:
        with time_limit(limit_s):
            outcome, detail = case()
    except Hang:
        outcome, detail = "hang", f"over {limit_s:g} s"
    except RecursionError as e:
        outcome, detail = "traceback", f"RecursionError: {str(e)[:120]}"
    except Exception as e:  # classifying every escape is the point
        outcome, detail = "traceback", f"{type(e).__name__}: {str(e)[:200]}"
    if outcome != "hang" and time.perf_counter() - t0 > limit_s:
        outcome, detail = "hang", f"took {time.perf_counter() - t0:.1f} s > {limit_s:g} s"
    tally.add(outcome, f"{describe()} -> {detail}" if outcome in BAD else "", detail)


NASTY = ["٣", "１", "1_0", "nan", "NaN", "inf", "-inf", "Infinity", "1e15", "1e308", "-1e308",
         "1e5", "100001", "0x10", "+5", "", " ", "\x00", "1\x00", "٣.٥", "۱۲", "𝟙", "²", "½",
         "1e-400", "9" * 400, "-0", "1,5", "\"", "'", "\u2028", "\u00a0", "1 2", "\t1"]


def rand_text(rng: random.Random, n: int = 12) -> str:
    """Random text from a mix of ASCII, controls and awkward Unicode."""
    pools = [
        "abcdefXYZ0123456789_.-",
        "()%;\"'\\[]{}<>#=!,:/ ",
        "\n\r\x00\t\x0b\x0c\x1b\x7f",
        "\u2028\u2029\u0085\ufeff\u200b\u00a0",
        "٣１²½éßЖ中𝟙",
    ]
    return "".join(rng.choice(rng.choice(pools)) for _ in range(rng.randint(0, n)))


def rand_cell(rng: random.Random) -> str:
    r = rng.random()
    if r < 0.55:
        return rng.choice(NASTY)
    if r < 0.85:
        return rand_text(rng)
    return repr(rng.uniform(-1e6, 1e6)) if rng.random() < 0.5 else str(rng.randint(-9, 10**6))


def short(data: object, n: int = 160) -> str:
    s = repr(data)
    return s if len(s) <= n else s[:n] + f"…(+{len(s) - n})"
