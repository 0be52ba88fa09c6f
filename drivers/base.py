"""The one async interface every CNC link implements (serial DNC, OPC UA, Modbus TCP, LinuxCNC).

Shaped after python-can's ``BusABC``: the public methods are the contract the daemon's session
uses; a transport declares what it can do in ``capabilities`` and the session adapts (a link
without ``start_request`` is only started from the HMI, the CAN panel or the CLI).
"""

from __future__ import annotations

import abc
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass

from contracts.jobs import ProgramJob, Verdict
from contracts.messages import ProbeHit
from contracts.temperatures import TemperatureChannel


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



class LinkError(Exception):
    """The link failed (connection lost, protocol violation, timeout); message says which."""


class ChannelMissing(LinkError):
    """A temperature channel's address does not exist on the controller (a node id or register
    misspelt in daemon.yaml): reading it again will not help."""


class ControllerAlarm(Exception):
    """The controller stopped the program with an alarm (e.g. probe did not trigger)."""


class ControllerAborted(ControllerAlarm):
    """The program was reset / aborted on the controller itself (the operator's RESET)."""


class CncLink(abc.ABC):
    """A connection to one CNC controller."""

    capabilities: Capabilities = Capabilities()
    uses_dialect: bool = False  # the link builds G-code itself (a DNC verdict program): the
    # registry hands it the machine's DialectCodec as ``dialect=``
    handshake: bool = False  # the program carries the result handshake (ring wait, stop flag:
    # contracts.result_lines.HANDSHAKE_VARIABLES): the link reads the controller's variables
    start_timeout_s: float = 0.0  # > 0: the program is started at the machine (its PLC or the
    # operator presses NC start, the control offers no remote start): the first result may take
    # this long, and the link says in its status that it waits for it (``on_step``)
    on_step: Callable[[str | None], None] | None = None  # set by the session: what the run
    # waits for at the machine now ("waiting for NC start …"), None once it runs

    def say_step(self, text: str | None) -> None:
        """Tell the session what the run waits for at the machine (None: nothing any more)."""
        if self.on_step is not None:
            self.on_step(text)

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
        with ``triggered=False`` is yielded before the alarm so it can be journaled. A link that
        stamps its hits' ``t_s`` (``drivers.hits.HitFactory``) starts ``job.clock`` (the run's,
        ``contracts.jobs.RunClock``) as it starts the program; one that leaves ``t_s`` at 0 has
        them stamped by the session on the same clock."""

    @abc.abstractmethod
    async def write_verdict(self, verdict: Verdict) -> None:
        """Write the verdict where the controller reads it (variable, register or node)."""

    @abc.abstractmethod
    async def abort(self) -> None:
        """Stop the running program on the controller (reset / cycle stop)."""

    @abc.abstractmethod
    async def close(self) -> None:
        """Close the connection; safe to call twice."""

    async def read_temperature(self, channel: TemperatureChannel) -> float:
        """The channel's value (°C) read from the controller now; ``LinkError`` saying why not.
        A link whose program prints its temperatures (DNC) returns them in ``printed``."""
        raise LinkError(f"the {type(self).__name__} cannot read temperature channel "
                        f"{channel.name} ({channel.address})")

    def printed_temperatures(self) -> list[tuple[int, str, float]]:
        """Temperatures the program printed since the last call: (channel number, 1-based
        among the program's printed channels; marker S start, P<pose>, E end; °C), e.g. a DNC
        program's macro-variable lines (``contracts.temperatures.parse_printed``); polled
        links print none."""
        return []
