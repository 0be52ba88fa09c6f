"""The one async interface every CNC link implements (serial DNC, OPC UA, Modbus TCP, LinuxCNC).

Shaped after python-can's ``BusABC``: the public methods are the contract the daemon's session
uses; a transport declares what it can do in ``capabilities`` and the session adapts (a link
without ``start_request`` is only started from the HMI, the CAN panel or the CLI).
"""

from __future__ import annotations

import abc
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from typing import Literal, Protocol

from daemon.messages import ProbeHit, TouchId

VerdictStatus = Literal["PASS", "WARN", "FAIL", "ERROR"]
VERDICT_CODES: dict[str, int] = {"PASS": 1, "WARN": 2, "FAIL": 3, "ERROR": 4}
"""Numeric verdict written to the CNC (variable, register or node); 0 = no verdict yet."""


class DialectCodec(Protocol):
    """What a link needs of a controller dialect, handed to it by the daemon (implemented by
    ``daemon.dialects.Dialect``): links never import the program generator."""

    name: str

    def parse_result(self, line: str) -> ProbeHit | None:
        """A touch's result line (DPRNT, WRITE, F-PRINT, LOG) → hit; None for other lines."""
        ...

    def verdict_program(self, code: int) -> str:
        """The small program that sets the controller's verdict variable to ``code``."""
        ...


@dataclass(frozen=True)
class Capabilities:
    start_request: bool = False  # the CNC can raise a start-of-shift request
    streams_blocks: bool = False  # program is drip-fed block by block (DNC, Modbus mailbox)
    loads_program: bool = False  # program is transferred whole, then started
    writes_verdict: bool = True
    can_abort: bool = True


@dataclass(frozen=True)
class StartRequest:
    """A start request raised by the controller (start of shift)."""

    source: str  # e.g. "cnc"
    machine: str = ""
    detail: str = ""


@dataclass(frozen=True)
class Verdict:
    status: VerdictStatus
    run_id: str
    summary: str = ""
    reasons: tuple[str, ...] = ()

    @property
    def code(self) -> int:
        return VERDICT_CODES[self.status]


@dataclass(frozen=True)
class ProgramJob:
    """What a link needs to run one verification program."""

    run_id: str
    text: str  # the whole program as the controller receives it
    dialect: str  # fanuc | siemens | heidenhain | linuxcnc
    touch_count: int
    meta: dict[str, str] = field(default_factory=dict)
    touches: tuple[TouchId, ...] = ()  # touch table by seq (seq k at index k-1): lets a link
    # that only receives (seq, axes) from the controller (OPC UA, Modbus) name pose/ball/touch
    files: dict[str, str] = field(default_factory=dict)  # auxiliary files the program needs on
    # the control (Heidenhain FN 16 format files); OPC UA transfers them with the program
    codec: DialectCodec | None = None  # decodes the program's result lines (links that read
    # the controller's printed output: serial DNC, LinuxCNC)


class LinkError(Exception):
    """The link failed (connection lost, protocol violation, timeout); message says which."""


class ControllerAlarm(Exception):
    """The controller stopped the program with an alarm (e.g. probe did not trigger)."""


class CncLink(abc.ABC):
    """A connection to one CNC controller."""

    capabilities: Capabilities = Capabilities()
    uses_dialect: bool = False  # the link builds G-code itself (a DNC verdict program): the
    # registry hands it the machine's DialectCodec as ``dialect=``

    @abc.abstractmethod
    async def connect(self) -> None:
        """Open the connection; raise ``LinkError`` with a clear reason when unreachable."""

    @abc.abstractmethod
    async def wait_start_request(self) -> StartRequest:
        """Block until the controller raises its start-of-shift request."""

    @abc.abstractmethod
    def run(self, job: ProgramJob) -> AsyncIterator[ProbeHit]:
        """Load or stream ``job``, start it, and yield every ``ProbeHit`` the moment it arrives.

        Ends when the program ends; raises ``ControllerAlarm`` or ``LinkError`` otherwise. A hit
        with ``triggered=False`` is yielded before the alarm so it can be journaled."""

    @abc.abstractmethod
    async def write_verdict(self, verdict: Verdict) -> None:
        """Write the verdict where the controller reads it (variable, register or node)."""

    @abc.abstractmethod
    async def abort(self) -> None:
        """Stop the running program on the controller (reset / cycle stop)."""

    @abc.abstractmethod
    async def close(self) -> None:
        """Close the connection; safe to call twice."""
