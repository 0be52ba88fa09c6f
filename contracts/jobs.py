"""What the daemon hands a link (``ProgramJob``, the dialect codec) and what it writes back
(``Verdict`` and its numeric code on the controller)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Literal, Protocol

from contracts.messages import ProbeHit
from contracts.touch_table import TouchTable

VerdictStatus = Literal["PASS", "WARN", "FAIL", "ERROR"]


VERDICT_CODES: dict[str, int] = {"PASS": 1, "WARN": 2, "FAIL": 3, "ERROR": 4}
"""Numeric verdict written to the CNC (variable, register or node); 0 = no verdict yet."""


class DialectCodec(Protocol):
    """What a link needs of a controller dialect, handed to it by the daemon (implemented by
    ``programs.dialects.Dialect``): links never import the program generator."""

    name: str

    def parse_result(self, line: str) -> ProbeHit | None:
        """A touch's result line (DPRNT, WRITE, F-PRINT, LOG) → hit; None for other lines."""
        ...

    def verdict_program(self, code: int) -> str:
        """The small program that sets the controller's verdict variable to ``code``."""
        ...

    def last_printed_seq(self, text: str) -> int:
        """The seq of the last touch whose result line ``text`` (the part of a program a DNC
        link fed) prints; 0 if none."""
        ...


@dataclass(frozen=True)
class Verdict:
    status: VerdictStatus
    run_id: str
    summary: str = ""
    reasons: tuple[str, ...] = ()

    @property
    def code(self) -> int:
        return VERDICT_CODES[self.status]


class RunClock:
    """The one clock of a run: every touch's and temperature reading's ``t_s`` (``ProbeHit``,
    ``TemperatureReading``, the probing log's column) is seconds since the run's first program
    started, on the daemon's monotonic clock, whichever program of the run (the plan's, a
    re-probe round's) it comes from.

    The session makes one per run and hands it to the link with every program
    (``ProgramJob.clock``); the link starts it when it starts the program (``start``: only the
    first program's start sets the origin), so the first program's times are those a link has
    always stamped and a later program's go on from them. Before the start it reads 0 (the
    run's start sample, taken before the program: the probing log has no negative times)."""

    def __init__(self) -> None:
        self.origin: float | None = None  # time.monotonic() of the first program's start

    @property
    def started(self) -> bool:
        return self.origin is not None

    def start(self, at: float | None = None) -> float:
        """A program starts (``at``: when, on ``time.monotonic()``; now by default): the first
        call sets the run's origin, later ones keep it. Returns this program's start on the
        run clock (0 for the first)."""
        now = time.monotonic() if at is None else at
        if self.origin is None:
            self.origin = now
        return max(now - self.origin, 0.0)

    def t_s(self) -> float:
        """Seconds since the run's first program started; 0 before it did."""
        return 0.0 if self.origin is None else max(time.monotonic() - self.origin, 0.0)


@dataclass(frozen=True)
class ProgramJob:
    """What a link needs to run one verification program."""

    run_id: str
    text: str  # the whole program as the controller receives it
    dialect: str  # one of contracts.result_lines.DIALECT_NAMES
    touch_count: int
    meta: dict[str, str] = field(default_factory=dict)
    touches: TouchTable = field(default_factory=TouchTable)  # the program's touches by seq:
    # a link that only receives (seq, axes) from the controller (OPC UA, Modbus) names the hit
    # here, and the session completes and checks every hit against the same table
    files: dict[str, str] = field(default_factory=dict)  # auxiliary files the program needs on
    # the control (Heidenhain FN 16 format files); OPC UA transfers them with the program
    codec: DialectCodec | None = None  # decodes the program's result lines (links that read
    # the controller's printed output: serial DNC, LinuxCNC)
    clock: RunClock = field(default_factory=RunClock, compare=False, repr=False)  # the run's
    # clock (a job of its own gets a fresh one): a link stamping hits starts it with the program
