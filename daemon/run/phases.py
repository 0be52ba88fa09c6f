"""The phases of a run (the state machine's states), why a start is refused or a run fails, run
ids, and the live status a session publishes: state, progress, time left, subscribers."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import secrets
import time
from collections.abc import Callable
from enum import StrEnum
from typing import Any

from daemon.machines.setup import MachineSetup
from daemon.store.journal import Store, validate_run_id

log = logging.getLogger("rumba.session")


class State(StrEnum):
    IDLE = "IDLE"
    PREPARE = "PREPARE"
    STREAM = "STREAM"
    CAPTURE = "CAPTURE"
    IDENTIFY = "IDENTIFY"
    JUDGE = "JUDGE"
    WRITE_BACK = "WRITE-BACK"
    ABORTED = "ABORTED"
    INTERRUPTED = "INTERRUPTED"
    FAILED = "FAILED"


READY_STATES = (State.IDLE, State.ABORTED, State.INTERRUPTED, State.FAILED)
"""States in which a new run may start (the last outcome stays visible until then).

How a run that did not reach its verdict ended, each with its phase and cause:
ABORTED, a person (HMI, CAN panel, a signal to ``rumba verify``) or the controller (a RESET the
link reports) stopped it; INTERRUPTED, rumba lost the run: the link dropped, the controller fell
silent (plain DNC cannot tell a RESET from a cut cable), the daemon stopped or crashed; FAILED,
the run went on but could not measure (probe did not trigger, a result not matching the program
or malformed, an alarm, an identification refused, a bug)."""

STOPPED_STATES = (State.ABORTED, State.INTERRUPTED, State.FAILED)
"""The end states without a verdict of the machine (ERROR is written back to the CNC)."""

END_READS = "after the last touch, while reading the end-of-run temperatures"
"""Where a run is that stops while it waits for its last temperature reads: the
program has ended, the state is still CAPTURE (no state of its own for the few seconds the
reads are bounded by), and "during CAPTURE" would tell the operator a touch was cut. The stop's
reason names this instead (``RunStatus.during``): composed once, the one text the HMI's status,
its run record and the journal show."""

START_READS = "before the program started, while reading the start-of-run temperatures"
"""Where a run is that stops while it waits for its first temperature reads: the
state is already STREAM (the program checked), yet none was loaded or sent, and "during STREAM"
would tell the operator the program was cut. Like ``END_READS``: the stop's reason, the HMI
status's ``step`` and its machine card show this one text."""


class Refused(Exception):
    """A start request was refused; the message says why (e.g. a run is in progress)."""


class RunFailed(Exception):
    """The run cannot continue; the message is the reason stored with the run."""


class ControllerSilent(Exception):
    """No result came for the touch timeout: the run is lost (INTERRUPTED), not failed; the
    message is the reason stored with the run."""


def new_run_id() -> str:
    """Sortable, unique and G-code safe (letters, digits, '-'), 29 characters: within
    ``daemon.store.journal.RUN_ID_PATTERN``, which every run id entering the journal must match.
    48 random bits: 100 daemons of a fleet starting in the same second collide with
    probability ~2e-11 (16 bits gave ~7 % every morning, and a fleet store refuses the loser)."""
    return validate_run_id(time.strftime("%Y%m%dT%H%M%SZ", time.gmtime()) + "-"
                           + secrets.token_hex(6))


class RunStatus:
    """The bookkeeping of one machine's runs: the phase, progress and verdict, published to
    every subscriber (HMI event streams) and listener (CAN lamps) on each change."""

    def __init__(self, setup: MachineSetup, store: Store) -> None:
        self.setup = setup
        self.store = store
        self.state = State.IDLE
        self.reason = ""
        self.run_id: str | None = None
        self.trigger = ""
        self.started_by = ""  # the HMI account that started the current run ('' otherwise)
        self.done = 0
        self.total = 0
        self.started_at = 0.0
        self.first_hit_at: float | None = None
        self.estimated_s: float | None = None
        self.verdict: dict[str, Any] | None = None
        # what the probe is on now: {"pose", "ball", "touch"} of the touch the
        # controller is at — the next one in the program's table once a hit has arrived
        self.probing: dict[str, Any] | None = None
        self._queues: set[asyncio.Queue] = set()
        self.listeners: list[Callable[[dict[str, Any]], None]] = []
        self.link_ok = True  # False after a lost link: the next run reconnects first
        # what the run does within its state where the state's name would misreport it to a
        # stop's reason and the HMI (START_READS, END_READS); cleared by the next state
        self._step: str | None = None

    @property
    def step(self) -> str | None:
        """The step within the state (``START_READS``, ``END_READS``), None outside them."""
        return self._step

    @step.setter
    def step(self, text: str | None) -> None:
        # published: the HMI's card shows the step the moment the run enters it, not CAPTURE
        # with every touch done for as long as the end's reads take
        if text != self._step:
            self._step = text
            self._publish()

    def during(self) -> str:
        """Where the run is, for a stop's reason: "during CAPTURE", or the step's own words."""
        return self._step or f"during {self.state}"

    @property
    def busy(self) -> bool:
        return self.state not in READY_STATES

    def status(self) -> dict[str, Any]:
        now = time.time()
        return {
            "machine": self.setup.name, "state": str(self.state), "reason": self.reason,
            "run_id": self.run_id, "trigger": self.trigger, "started_by": self.started_by,
            "done": self.done,
            "total": self.total, "elapsed_s": round(now - self.started_at, 1)
            if self.run_id else None, "eta_s": self.eta_s(now), "verdict": self.verdict,
            "busy": self.busy, "link_ok": self.link_ok,
            "probing": self.probing if self.busy else None,
            "step": self._step if self.busy else None,  # START_READS, END_READS, or null
            "job": getattr(self, "job", "check"),  # "check", or "map" (run/map_job.py)
            "map_job": {"name": mj.name, "placements": len(mj.placements)}
            if (mj := getattr(self.setup, "map_job", None)) else None,
            # a map job's operator prompt between placements (the HMI's Continue), or null
            "prompt": prompt.as_dict() if (prompt := getattr(self, "prompt", None)) else None,
            "map": getattr(self, "map_result", None),  # a map run's figure status and JSON
        }

    def _probing(self, touch: Any) -> None:
        """The pose, ball and touch the probe is on (a hit, or the table's next touch)."""
        tid = getattr(touch, "id", touch)
        if tid is not None:
            self.probing = {"pose": tid.pose, "ball": tid.ball, "touch": tid.touch}

    def eta_s(self, now: float | None = None) -> float | None:
        """Time left: measured pace once touches arrive, else the program's estimate."""
        if not self.busy or getattr(self, "prompt", None) is not None:
            return None  # idle, or a map job waiting for its operator: no machine time runs
        now = time.time() if now is None else now
        if self.first_hit_at is not None and self.done >= 2:
            pace = (now - self.first_hit_at) / (self.done - 1)
            return round(max(self.total - self.done, 0) * pace, 1)
        if self.estimated_s is not None:
            return round(max(self.estimated_s - (now - self.started_at), 0.0), 1)
        return None

    def subscribe(self) -> asyncio.Queue:
        q: asyncio.Queue = asyncio.Queue(maxsize=64)
        self._queues.add(q)
        q.put_nowait(self.status())
        return q

    def unsubscribe(self, q: asyncio.Queue) -> None:
        self._queues.discard(q)

    def set_link_ok(self, ok: bool) -> None:
        """Record whether the link is up (the service's start-request watcher loses it too)
        and show it on every status subscriber."""
        self.link_ok = ok
        self._publish()

    def _publish(self) -> None:
        st = self.status()
        for q in self._queues:
            if q.full():  # a slow browser loses intermediate frames, never the latest
                with contextlib.suppress(asyncio.QueueEmpty):
                    q.get_nowait()
            q.put_nowait(st)
        for fn in self.listeners:
            try:
                fn(st)
            except Exception:  # a lamp must never break a run
                log.exception("status listener failed")

    def _enter(self, state: State, reason: str | None = None) -> None:
        self.state, self._step = state, None
        if reason is not None:
            self.reason = reason
        if self.run_id is not None:
            self.store.set_state(self.run_id,
                                 "DONE" if state == State.IDLE else str(state), reason)
        log.info("%s %s %s%s", self.setup.name, self.run_id, state,
                 f": {reason}" if reason else "")
        self._publish()
