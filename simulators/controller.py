"""The virtual CNC: executes a program of any dialect on the true machine, block by block.

Protocol front-ends (simulators/serve.py, simulators/frontends/) sit on top of this one API:
whole-program load or DNC drip-feed, start / abort / feed hold, controller state and alarms,
macro/R/Q variables, an event stream (output lines, touch results, state changes, blocks) and
the start-of-shift handshake (request / busy / done / verdict). Machine time comes from the
motion (rapid, feed, rotary index with clamping, dwell); ``time_scale`` 0 runs as fast as
possible, 1 in real time.
"""

from __future__ import annotations

import asyncio
import contextlib
from dataclasses import dataclass, field

import numpy as np

from contracts.messages import TOUCH_DIRECTIONS
from simulators.faults import FRONT_END_KINDS, Fault, FaultPlan
from simulators.gcode import Alarm, ProbeOutcome, make_interpreter, run
from simulators.probe import collision, first_contact
from simulators.truth import TruthModel

RESULT_SLOTS = 8  # ring of result slots (gcode_templates/README.md)
VERDICT_VARIABLE = {"fanuc": "#598", "haas": "#598", "siemens": "R4", "heidenhain": "Q1598",
                    "linuxcnc": "#3998"}
"""Where the CNC's start-of-shift macro reads the verdict (gcode_templates/*/README.md): a
program writing it (a DNC link's verdict program) delivers the verdict, and a verdict written
by OPC UA or Modbus appears in it too, so one macro serves every transport."""
TOOL_CHANGE_S = 5.0


# ------------------------------------------------------------------------------ events


@dataclass(frozen=True)
class PrintLine:
    text: str


@dataclass(frozen=True)
class TouchResult:
    slot: int  # (seq - 1) mod RESULT_SLOTS
    seq: int  # 1-based probing move number in the program
    values: dict[str, float]  # X Y Z (mm) and b c (deg), latched (end point on a miss)
    triggered: bool


@dataclass(frozen=True)
class StateChange:
    state: str
    alarm: str | None


@dataclass(frozen=True)
class Block:
    number: int  # 1-based line of the program


@dataclass(frozen=True)
class RequestRaised:
    """The start-of-shift macro asked for a run (a serial front-end prints its request line)."""

    machine: str


@dataclass(frozen=True)
class FaultEvent:
    kind: str
    fault: Fault


ControllerEvent = PrintLine | TouchResult | StateChange | Block | FaultEvent | RequestRaised


class _Variables(dict):
    """Macro / R / Q variables; every write is reported (the verdict variable is watched)."""

    def __init__(self, on_write) -> None:  # type: ignore[no-untyped-def]
        super().__init__()
        self._on_write = on_write

    def __setitem__(self, key: str, value: float | str) -> None:
        super().__setitem__(key, value)
        self._on_write(key, value)


@dataclass
class TouchRecord:
    """Everything the controller knows about one probing move (for the offline log)."""

    seq: int
    t_s: float
    start: np.ndarray
    end: np.ndarray
    latched: dict[str, float]
    triggered: bool
    feed_mm_min: float
    touch: int  # 1..5 recognised from the move direction, 0 otherwise
    direction: tuple[float, float, float]
    ball: int  # ball index the move aims at (nearest nominal centre), -1 none
    contact_target: int | None  # what the stylus met (ball index, -1-k obstacle), None


# ------------------------------------------------------------------------- block source


class _Blocks:
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


# ------------------------------------------------------------------------- controller


@dataclass
class _Visit:
    key: tuple = ()
    noise_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))
    touches: set[int] = field(default_factory=set)


class VirtualController:
    """A CNC controller executing our programs on a ``TruthModel``."""

    def __init__(self, truth: TruthModel, *, time_scale: float = 0.0, rng_seed: int = 0,
                 faults: FaultPlan | None = None, dialect: str = "fanuc",
                 tnc_measuring_path_mm: float = 4.0, tnc_probe_feed_mm_min: float = 300.0
                 ) -> None:
        self.truth = truth
        self.time_scale = float(time_scale)
        self.rng_seed = rng_seed
        self.faults = faults or FaultPlan()
        self.dialect = dialect
        self.tnc_measuring_path_mm = tnc_measuring_path_mm
        self.tnc_probe_feed_mm_min = tnc_probe_feed_mm_min
        self.state = "idle"
        self.alarm: str | None = None
        self.machine_time_s = 0.0
        self._dialect_now = dialect
        self.variables: dict[str, float | str] = _Variables(self._variable_written)
        self.files: dict[str, str] = {}  # the control's file store (F-PRINT format files …)
        self.messages: list[str] = []
        self.printed: list[str] = []  # output lines of the current/last program
        self.touches: list[TouchRecord] = []
        self.front_faults: set[str] = set()  # active transport faults for the front-ends
        self.request = False
        self.busy = False
        self.done = False
        self._verdict = 0
        self.verdict = 0
        # What the start-of-shift macro prints after RUMBA REQUEST (Fanuc text: upper case).
        self.machine_id = "".join(ch for ch in truth.machine.name.upper()
                                  if ch.isalnum() or ch in "_.-")[:32] or "CNC"
        self.axes = ("X", "Y", "Z", *truth.rotary_letters)
        self._pos = {a: 0.0 for a in self.axes}
        self._pos["Z"] = self.reference("Z")
        self._subs: list[asyncio.Queue] = []
        self._blocks: _Blocks | None = None
        self._task: asyncio.Task | None = None
        self._resume = asyncio.Event()
        self._resume.set()
        self._finished = asyncio.Event()
        self._pending_s = 0.0
        self._visit = _Visit()
        self._rotary_moves = 0
        self._drop_lines = 0
        self._seq = 0
        self._rng = np.random.default_rng(rng_seed)
        self._nominal_cache: dict[tuple[float, float], np.ndarray] = {}
        self._deferring = False
        self._deferred: list[ControllerEvent] = []
        self._line_no, self._line_text = 0, ""

    # ---------------------------------------------------------------- public API
    def subscribe(self) -> asyncio.Queue:
        q: asyncio.Queue = asyncio.Queue()
        self._subs.append(q)
        return q

    def unsubscribe(self, q: asyncio.Queue) -> None:
        with contextlib.suppress(ValueError):
            self._subs.remove(q)

    async def load_program(self, text: str, dialect: str, files: dict[str, str] | None = None
                           ) -> None:
        """Load a whole program (and auxiliary files such as Heidenhain F-PRINT formats)."""
        if self.state in ("running", "hold"):
            raise RuntimeError(f"cannot load a program while {self.state}")
        make_interpreter(dialect, self)  # validates the dialect name now
        self.files.update(files or {})
        self._blocks = _Blocks()
        self._blocks.extend(text.replace("\r\n", "\n").replace("\r", "\n").split("\n"))
        self._blocks.close()
        self._dialect_now = dialect
        self._set_state("idle", self.alarm)

    async def start(self) -> None:
        """Cycle start: run the loaded program in a background task (or resume a hold)."""
        if self.state == "hold":
            self._resume.set()
            self._set_state("running", None)
            return
        if self.state == "running":
            return
        if self._blocks is None:
            raise RuntimeError("no program loaded")
        self._begin()

    async def feed_block(self, line: str) -> None:
        """DNC drip-feed: one block; the first block of a stream starts execution. Blocks
        after the program's end (M30 …) up to ``end_of_stream`` are ignored, as on a control
        that has finished its tape."""
        if (self._blocks is not None and not self._blocks.complete
                and self.state in ("done", "alarm")):
            return
        if self._blocks is None or self._blocks.complete or self.state not in (
                "running", "hold"):
            if self.state in ("running", "hold"):
                raise RuntimeError("a program is already running")
            self._blocks = _Blocks()
            self._dialect_now = self.dialect
            self._blocks.extend([line.rstrip("\r\n")])
            self._begin()
            return
        self._blocks.extend([line.rstrip("\r\n")])
        await asyncio.sleep(0)

    async def end_of_stream(self) -> None:
        if self._blocks is not None:
            self._blocks.close()

    async def abort(self) -> None:
        """Reset: stop at once; state idle (the alarm text is kept until the next start)."""
        task = self._task
        if task is not None and not task.done():
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self._resume.set()
        if self._blocks is not None:
            self._blocks.close()
        self._flush()
        self._set_state("idle", self.alarm)
        self._finished.set()

    async def wait_done(self, timeout: float | None = None) -> str:
        if self._task is not None:
            await asyncio.wait_for(self._finished.wait(), timeout)
        return self.state

    def raise_start_request(self) -> None:
        """What the CNC's start-of-shift macro does: clear the verdict variable, ask for a
        verification run (a flag for OPC UA / Modbus, a printed request line for DNC)."""
        self.request, self.done, self.verdict = True, False, 0
        self._emit(StateChange(self.state, self.alarm))
        self._emit(RequestRaised(self.machine_id))

    @property
    def verdict(self) -> int:
        """0 none yet, 1 PASS, 2 WARN, 3 FAIL, 4 ERROR (drivers/README.md)."""
        return self._verdict

    @verdict.setter
    def verdict(self, code: int) -> None:
        # Written by a front-end (OPC UA node, Modbus register): the macro variable shows it.
        self._verdict = int(code)
        name = VERDICT_VARIABLE.get(self._dialect_now)
        if name is not None:
            dict.__setitem__(self.variables, name, float(code))

    def _variable_written(self, name: str, value: float | str) -> None:
        """A program wrote a variable: the verdict variable is the verdict arriving (DNC)."""
        if name != VERDICT_VARIABLE.get(self._dialect_now) or isinstance(value, str):
            return
        code = round(float(value))
        self._verdict = code if 0 <= code <= 4 else 0
        self.done = self._verdict != 0

    def reseed(self, seed: int) -> None:
        """Restart the probing-noise sequence: a run's noise no longer depends on the runs
        before it on this controller (tests sharing one simulated CNC)."""
        self.rng_seed = seed
        self._rng = np.random.default_rng(seed)
        self._visit = _Visit()

    def feed_hold(self) -> None:
        if self.state == "running":
            self._resume.clear()
            self._set_state("hold", None)

    def reference(self, axis: str) -> float:
        """Reference (home) position: top of the Z travel (controller axes show the tool's
        motion relative to the workpiece, whatever moves), zero elsewhere."""
        return float(self.truth.machine.axes[axis].travel[1]) if axis == "Z" else 0.0

    # ---------------------------------------------------------------- MachineIO
    def position(self) -> dict[str, float]:
        return dict(self._pos)

    def _q(self, pos: dict[str, float]) -> np.ndarray:
        return np.array([pos[a] for a in self.axes], float)

    def _check_travel(self, target: dict[str, float]) -> None:
        for a in self.axes:
            lo, hi = self.truth.machine.axes[a].travel
            if not lo - 1e-9 <= target[a] <= hi + 1e-9:
                raise Alarm(f"OVERTRAVEL {a}{target[a]:+.4f} outside [{lo:g}, {hi:g}]")

    def move(self, target: dict[str, float], feed_mm_min: float | None) -> None:
        self._check_travel(target)
        q0, q1 = self._q(self._pos), self._q(target)
        hit = collision(self.truth, q0, q1, self.machine_time_s + self._pending_s)
        if hit:
            raise Alarm(f"PROBE COLLISION: {hit} on the move to "
                        + " ".join(f"{a}{target[a]:.4f}" for a in self.axes))
        dyn = self.truth.machine_file.dynamics
        lin = float(np.linalg.norm(q1[:3] - q0[:3]))
        rot = float(np.max(np.abs(q1[3:] - q0[3:])))
        if feed_mm_min is None:
            dt = max(np.max(np.abs(q1[:3] - q0[:3])) / dyn.rapid_mm_min,
                     rot / dyn.rotary_rapid_deg_min) * 60.0
        else:
            dt = (lin if lin > 0 else rot) / min(feed_mm_min, dyn.max_feed_mm_min) * 60.0
        if rot > 0:
            dt += dyn.rotary_clamp_s  # unclamp + clamp of the indexed axes
            self._rotary_moves += 1
        self._pending_s += dt
        self._pos = dict(target)

    def dwell(self, seconds: float) -> None:
        if seconds < 0:
            raise Alarm("negative dwell")
        self._pending_s += seconds

    def output(self, text: str) -> None:
        if self._drop_lines > 0:
            self._drop_lines -= 1
            return
        self.printed.append(text)
        self._emit(PrintLine(text))

    def message(self, text: str) -> None:
        self.messages.append(text)

    def probe(self, target: dict[str, float], feed_mm_min: float) -> ProbeOutcome:
        truth = self.truth
        self._check_travel(target)
        self._seq += 1
        seq = self._seq
        t = self.machine_time_s + self._pending_s
        dyn = truth.machine_file.dynamics
        if feed_mm_min > dyn.max_probe_feed_mm_min:
            raise Alarm(f"probing feed F{feed_mm_min:g} above the machine's limit "
                        f"{dyn.max_probe_feed_mm_min:g}")
        p0, p1 = self._q(self._pos)[:3], self._q(target)[:3]
        b, c = self._pos[self.axes[3]], self._pos[self.axes[4]]
        if target[self.axes[3]] != b or target[self.axes[4]] != c:
            raise Alarm("rotary axes must not move during a probing move")
        length = float(np.linalg.norm(p1 - p0))
        if length <= 0:
            raise Alarm("probing move of zero length")
        u = (p1 - p0) / length
        touch, direction = self._touch_number(u)
        ball = self._aimed_ball(p1, b, c)
        faults = self.faults.due({"no_trigger", "early_trigger", "drop_result_line"},
                                 touch=seq, t_s=t)
        kinds = {f.kind for f in faults}
        for f in faults:
            self._emit(FaultEvent(f.kind, f))
            if f.kind == "drop_result_line":
                self._drop_lines += f.params.get("lines", 1)
        contact = None if "no_trigger" in kinds else first_contact(truth, p0, p1, b, c, t)
        s_latch = None
        target_id = None
        if "early_trigger" in kinds:
            frac = next(f.fraction for f in faults if f.kind == "early_trigger")
            if contact is None or frac < contact.s:
                s_latch, target_id = frac, -999
        if s_latch is None and contact is not None:
            s_latch = contact.s + truth.errors.probe.pretravel_um * 1e-3 / length
            target_id = contact.target
            if s_latch > 1.0:
                s_latch = None  # the move ended before the probe switched
        if s_latch is None:
            latched_xyz = p1.copy()
            stop = p1
            triggered = False
        else:
            stop = p0 + s_latch * (p1 - p0)
            latched_xyz = stop + self._latch_errors(u, t, b, c, touch, direction, stop,
                                                    target_id if target_id is not None
                                                    and target_id >= 0 else ball)
            triggered = True
        self._pending_s += length * (s_latch if s_latch is not None else 1.0) / feed_mm_min * 60
        self._pos.update({"X": stop[0], "Y": stop[1], "Z": stop[2]})
        latched = {"X": float(latched_xyz[0]), "Y": float(latched_xyz[1]),
                   "Z": float(latched_xyz[2]), self.axes[3]: b, self.axes[4]: c}
        self.touches.append(TouchRecord(seq, t, p0, p1, latched, triggered, feed_mm_min,
                                        touch, direction, ball, target_id))
        self._emit(TouchResult((seq - 1) % RESULT_SLOTS, seq,
                               {"X": latched["X"], "Y": latched["Y"], "Z": latched["Z"],
                                "b": b, "c": c}, triggered))
        return ProbeOutcome(triggered, latched)

    # ------------------------------------------------------------ probe helpers
    def _touch_number(self, u: np.ndarray) -> tuple[int, tuple[float, float, float]]:
        """Touch 1..5 from the move direction (controller X Y Z = tool relative to workpiece);
        the pole comes against the spindle axis."""
        dirs = dict(TOUCH_DIRECTIONS)
        dirs[5] = tuple(-np.asarray(self.truth.machine.spindle_axis, float))
        best, k = max((float(np.dot(u, d)), k) for k, d in dirs.items())
        if best > 0.999:
            return k, tuple(float(x) for x in dirs[k])
        return 0, tuple(float(x) for x in u)

    def _aimed_ball(self, end: np.ndarray, b: float, c: float) -> int:
        key = (round(b, 6), round(c, 6))
        if key not in self._nominal_cache:
            n = len(self.truth.artefact.balls)
            self._nominal_cache[key] = np.array(
                [self.truth.centre_ctrl(i, b, c, nominal=True) for i in range(n)])
        d = np.linalg.norm(self._nominal_cache[key] - end, axis=1)
        return int(np.argmin(d))

    def _latch_errors(self, u: np.ndarray, t: float, b: float, c: float, touch: int,
                      direction: tuple, stop: np.ndarray, ball: int) -> np.ndarray:
        """Effect offsets + probing noise: per touch along the approach, per ball visit common
        to its touches (thesis §3.4 repeatability)."""
        probe = self.truth.errors.probe
        # A visit ends when the ball or the indexation changes, or a touch number comes back
        # (the next repeat of the same ball). The generator orders the four equator touches by
        # path length, so touch numbers need not increase within one visit.
        key = (ball, round(b, 6), round(c, 6), self._rotary_moves)
        if key != self._visit.key or touch in self._visit.touches:
            self._visit = _Visit(key, self._rng.normal(0.0, 1.0, 3)
                                 * np.asarray(probe.centre_noise_um) * 1e-3)
        self._visit.touches.add(touch)
        noise = self._visit.noise_mm + u * self._rng.normal(0.0, probe.touch_noise_um * 1e-3)
        try:
            eff = self.truth.touch_offset_mm(t, b, c, ball, touch, np.asarray(direction), stop)
        except ValueError as e:
            raise Alarm(f"simulator effect model: {e}") from None
        return eff + noise

    # ---------------------------------------------------------------- running
    def _begin(self) -> None:
        self.alarm = None
        self.machine_time_s = 0.0
        self._pending_s = 0.0
        self._seq = 0
        self.touches = []
        self.printed = []
        self._finished.clear()
        self._resume.set()
        self._set_state("running", None)
        self._task = asyncio.get_running_loop().create_task(self._run())

    async def _run(self) -> None:
        assert self._blocks is not None
        opts = {}
        if self._dialect_now == "heidenhain":
            opts = {"files": self.files, "measuring_path_mm": self.tnc_measuring_path_mm,
                    "probe_feed_mm_min": self.tnc_probe_feed_mm_min,
                    "stylus_radius_mm": self.truth.stylus_radius_mm}
        interp = make_interpreter(self._dialect_now, self, self.variables, **opts)
        try:
            await run(interp, self._blocks, self._before_block, self._program_stop)
            await self._advance_time()
            self._set_state("done", None)
        except Alarm as e:
            await self._advance_time()
            # Like a control's alarm screen: the message and the block it stopped in.
            self._set_state("alarm", f"{e} (line {self._line_no}: {self._line_text[:60]})")
        except asyncio.CancelledError:
            raise
        except Exception as e:  # a simulator defect must still end the program visibly
            self._flush()
            self._set_state("alarm", f"simulator error: {type(e).__name__}: {e}")
        finally:
            self._finished.set()

    async def _advance_time(self) -> None:
        """Let the machine time of the last block pass (scaled), then publish what the block
        produced: a result line appears when the probing move is over, not when it starts."""
        dt, self._pending_s = self._pending_s, 0.0
        self.machine_time_s += dt
        if self.time_scale > 0 and dt > 0:
            await asyncio.sleep(dt * self.time_scale)
        self._flush()

    def _flush(self) -> None:
        self._deferring = False
        events, self._deferred = self._deferred, []
        for ev in events:
            self._emit(ev)

    async def _before_block(self, index: int, block: str) -> None:
        await self._advance_time()
        number = index + 1
        self._line_no, self._line_text = number, block.strip()
        if self._subs:
            self._emit(Block(number))
        for f in self.faults.due(set(FRONT_END_KINDS) | {"alarm", "feed_hold", "restart",
                                                          "drop_result_line"},
                                 block=number, t_s=self.machine_time_s):
            self._emit(FaultEvent(f.kind, f))
            if f.kind in FRONT_END_KINDS:
                self.front_faults.add(f.kind)
            elif f.kind == "alarm":
                raise Alarm(f.message)
            elif f.kind == "drop_result_line":
                self._drop_lines += f.params.get("lines", 1)
            elif f.kind == "feed_hold":
                self.feed_hold()
                if f.duration_s > 0:  # a timed hold: the machine stands, then goes on
                    self._pending_s += f.duration_s
                    asyncio.get_running_loop().call_later(f.duration_s * self.time_scale,
                                                          self._auto_resume)
            elif f.kind == "restart":
                self._restart()
                raise asyncio.CancelledError
        if not self._resume.is_set():
            await self._resume.wait()
        if self.time_scale <= 0 and index % 64 == 0:
            await asyncio.sleep(0)  # let abort / front-ends in
        self._deferring = True

    async def _program_stop(self) -> None:
        """M00 / #3006 / STOP: hold until cycle start (``start()``)."""
        await self._advance_time()
        self.feed_hold()
        await self._resume.wait()

    def _auto_resume(self) -> None:
        if self.state == "hold":
            self._resume.set()
            self._set_state("running", None)

    def _restart(self) -> None:
        """Power cycle: program gone, non-retained variables cleared (Fanuc #1-#199, R and
        Q parameters are kept as on a real control's retained memory from #500 / R / Q)."""
        for k in [k for k in self.variables if k.startswith("#") and k[1:].isdigit()
                  and int(k[1:]) < 500]:
            del self.variables[k]
        self._blocks = None
        self.alarm = None
        self._set_state("idle", None)

    def _set_state(self, state: str, alarm: str | None) -> None:
        changed = (state, alarm) != (self.state, self.alarm)
        self.state, self.alarm = state, alarm if state == "alarm" else (
            self.alarm if state == "idle" else None)
        if changed:
            self._emit(StateChange(self.state, self.alarm))

    def _emit(self, ev: ControllerEvent) -> None:
        if self._deferring:
            self._deferred.append(ev)
            return
        for q in self._subs:
            q.put_nowait(ev)
