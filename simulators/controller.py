"""The virtual CNC: executes a program of any dialect on the true machine, block by block.

Protocol front-ends (simulators/serve.py, simulators/frontends/) sit on top of this one API:
whole-program load or DNC drip-feed, start / abort / feed hold, controller state and alarms,
macro/R/Q variables, an event stream (output lines, touch results, state changes, blocks) and
the start-of-shift handshake (request / busy / done / verdict). Machine time comes from the
motion (rapid, feed, rotary index with clamping, dwell); ``time_scale`` 0 runs as fast as
possible, 1 in real time. ``machine_time_s`` counts from the program's start (touch times,
timed faults, the published machine time); the warm-up runs on ``thermal_time_s``, from the
simulated machine's start, on across programs.
"""

from __future__ import annotations

import asyncio
import contextlib

from contracts.controller_kinematics import controller_kinematics
from contracts.dialects import DIALECTS
from contracts.result_lines import VERDICT_VARIABLES as VERDICT_VARIABLE
from simulators.controller_events import (
    Block,
    ControllerEvent,
    EventStream,
    FaultEvent,
    PrintLine,
    RequestRaised,
    StateChange,
    TouchResult,
)
from simulators.controller_io import MachineSide
from simulators.controller_kinematics import KinematicsStore
from simulators.faults import FRONT_END_KINDS, FaultPlan
from simulators.gcode import Alarm, BlockQueue, ProbeOutcome, make_interpreter, run
from simulators.latch import ProbeLatch, TouchRecord
from simulators.thermal import PRINTED_VARIABLES
from simulators.truth import TruthModel

__all__ = [  # the events and the touch types are re-exported: callers import them from here
    "VERDICT_VARIABLE", "Block", "ControllerEvent", "FaultEvent", "MachineSide", "PrintLine",
    "ProbeOutcome", "RequestRaised", "StateChange", "TouchRecord", "TouchResult",
    "VirtualController",
]

# VERDICT_VARIABLE: where the CNC's start-of-shift macro reads the verdict (gcode_templates/*/
# README.md): a program writing it (a DNC link's verdict program) delivers the verdict, and a
# verdict written by OPC UA or Modbus appears in it too, so one macro serves every transport.


class _Variables(dict):
    """Macro / R / Q variables; every write is reported (the verdict variable is watched)."""

    def __init__(self, on_write) -> None:  # type: ignore[no-untyped-def]
        super().__init__()
        self._on_write = on_write

    def __setitem__(self, key: str, value: float | str) -> None:
        super().__setitem__(key, value)
        self._on_write(key, value)


class VirtualController(MachineSide):
    """A CNC controller executing our programs on a ``TruthModel`` (its machine side, the
    interpreter's MachineIO, is ``MachineSide``)."""

    def __init__(self, truth: TruthModel, *, time_scale: float = 0.0, rng_seed: int = 0,
                 faults: FaultPlan | None = None, dialect: str = "fanuc",
                 tnc_measuring_path_mm: float = 4.0, tnc_probe_feed_mm_min: float = 300.0,
                 kinematics: KinematicsStore | None = None) -> None:
        self.truth = truth
        # The control's kinematic values (simulators/controller_kinematics.py): compensation
        # writes go here, never to the truth; default: the machine file's section, if any.
        self.kinematics = kinematics if kinematics is not None else _store_of(truth)
        self.time_scale = float(time_scale)
        self.rng_seed = rng_seed
        self.faults = faults or FaultPlan()
        self.dialect = dialect
        self.tnc_measuring_path_mm = tnc_measuring_path_mm
        self.tnc_probe_feed_mm_min = tnc_probe_feed_mm_min
        self.state = "idle"
        self.alarm: str | None = None
        self.resets = 0  # RESETs so far: a tape reader tells a tape read across one (DNC)
        self.machine_time_s = 0.0
        self._warm_s = 0.0  # machine time of the programs before this one (thermal clock)
        self._dialect_now = dialect
        self.variables: dict[str, float | str] = _Variables(self._variable_written)
        # told of every variable write, the program's and a front-end's (name, value), in
        # order: a front-end publishing the controller's variables (R parameters over OPC UA,
        # macro variables over the Haas data port) and the ring pacing listen here
        self.variable_listeners: list = []
        self._blocks_run = 0
        self.files: dict[str, str] = {}  # the control's file store (F-PRINT format files …)
        self.messages: list[str] = []
        self.printed: list[str] = []  # output lines of the current/last program
        self.print_files: dict[str, list[str]] = {}  # FN 16 output files by name (TNC)
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
        self._events = EventStream()
        self._blocks: BlockQueue | None = None
        self._task: asyncio.Task | None = None
        self._resume = asyncio.Event()
        self._resume.set()
        self._finished = asyncio.Event()
        self._pending_s = 0.0
        self._latch = ProbeLatch(truth, rng_seed)
        self._rotary_moves = 0
        self._drop_lines = 0
        self._seq = 0
        self._line_no, self._line_text = 0, ""

    # ---------------------------------------------------------------- public API
    def subscribe(self) -> asyncio.Queue:
        return self._events.subscribe()

    def unsubscribe(self, q: asyncio.Queue) -> None:
        self._events.unsubscribe(q)

    async def load_program(self, text: str, dialect: str, files: dict[str, str] | None = None
                           ) -> None:
        """Load a whole program (and auxiliary files such as Heidenhain F-PRINT formats)."""
        if self.state in ("running", "hold"):
            raise RuntimeError(f"cannot load a program while {self.state}")
        make_interpreter(dialect, self)  # validates the dialect name now
        self.files.update(files or {})
        self._blocks = BlockQueue()
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
            self._blocks = BlockQueue()
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
        self.resets += 1
        task = self._task
        if task is not None and not task.done():
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self._resume.set()
        if self._blocks is not None:
            self._blocks.close()
        # Reset unloads: a later cycle start must not resume the aborted program, and the next
        # LoadProgram / drip-fed tape is a new program.
        self._blocks = None
        self._events.flush()
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
        name = getattr(DIALECTS.get(self._dialect_now), "verdict_variable", None)
        if name is not None:
            dict.__setitem__(self.variables, name, float(code))

    def _variable_written(self, name: str, value: float | str) -> None:
        """A program wrote a variable: the verdict variable is the verdict arriving (DNC)."""
        for listener in list(self.variable_listeners):
            listener(name, value)
        verdict_name = getattr(DIALECTS.get(self._dialect_now), "verdict_variable", None)
        if name != verdict_name or isinstance(value, str):
            return
        code = round(float(value))
        self._verdict = code if 0 <= code <= 4 else 0
        self.done = self._verdict != 0

    def reseed(self, seed: int) -> None:
        """Restart the probing-noise sequence: a run's noise no longer depends on the runs
        before it on this controller (tests sharing one simulated CNC)."""
        self.rng_seed = seed
        self._latch.reseed(seed)

    def move_artefact(self, truth: TruthModel) -> None:
        """The operator moved the balls (a map job's next placement): ``truth``, same machine."""
        self.truth, self._latch = truth, ProbeLatch(truth, self.rng_seed)

    def halcmd_setp(self, pin: str, value: float) -> None:
        """``halcmd setp pin value`` on the simulated LinuxCNC (its compensation is halcmd
        lines, not G-code); only a declared kins pin: ``KeyError`` otherwise."""
        self._kinematics_for(("hal_pin",)).write(pin, value, "halcmd setp")

    def operator_entry(self, address: str, value: float) -> None:
        """What the operator types in on a Haas settings page or the Heidenhain kinematics
        table (these controls have no program write of these values); declared addresses
        only: ``KeyError`` otherwise."""
        self._kinematics_for(("setting", "table_row")).write(address, value, "operator")

    def _kinematics_for(self, styles: tuple[str, ...]) -> KinematicsStore:
        rec = DIALECTS.get(getattr(self.kinematics, "family", ""))  # styles: its address forms
        if self.kinematics is None or rec is None or rec.kinematics_address not in styles:
            families = [n for n, r in DIALECTS.items() if r.kinematics_address in styles]
            raise KeyError(f"this control keeps no {'/'.join(families)} kinematic values")
        return self.kinematics

    @property
    def thermal_time_s(self) -> float:
        """The warm-up's clock: machine time since the simulated machine started (the truth's
        ``start_state``), every program so far; a re-probe round or the next run meets the
        machine as warm as the last program left it (a power-cycle fault leaves it warm too)."""
        return self._warm_s + self.machine_time_s

    def sensor_temperatures(self) -> dict[str, float]:
        """The structure sensors now (°C per axis with a warm-up; {} without): the same thermal
        state as the TCP drift of the touches (simulators/thermal.py)."""
        th = self.truth.thermal
        return {} if th is None else th.temperatures_c(self.thermal_time_s)

    def feed_hold(self) -> None:
        if self.state == "running":
            self._resume.clear()
            self._set_state("hold", None)

    def reference(self, axis: str) -> float:
        """Reference (home) position: top of the Z travel (controller axes show the tool's
        motion relative to the workpiece, whatever moves), zero elsewhere."""
        return float(self.truth.machine.axes[axis].travel[1]) if axis == "Z" else 0.0

    # ---------------------------------------------------------------- running
    def _begin(self) -> None:
        self.alarm = None
        # The program clock restarts, the thermal one runs on (idle time between programs is
        # not counted: the axes stand still and time_scale 0 has none).
        self._warm_s += self.machine_time_s
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
        opts = {"files": self.files, "measuring_path_mm": self.tnc_measuring_path_mm,
                "probe_feed_mm_min": self.tnc_probe_feed_mm_min,  # its record names those it takes
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
            self._events.flush()
            self._set_state("alarm", f"simulator error: {type(e).__name__}: {e}")
        finally:
            self._finished.set()

    async def _advance_time(self) -> None:
        """Let the machine time of the last block pass (scaled), then publish what the block
        produced: a result line appears when the probing move is over, not when it starts."""
        dt, self._pending_s = self._pending_s, 0.0
        self.machine_time_s += dt
        for axis, value in self.sensor_temperatures().items():  # as a PMC / PLC keeps them
            for names in PRINTED_VARIABLES:  # #59x, R9x, Q9x: one store, distinct names
                dict.__setitem__(self.variables, names[axis], value)
        if self.time_scale > 0 and dt > 0:
            await asyncio.sleep(dt * self.time_scale)
        self._events.flush()

    async def _before_block(self, index: int, block: str) -> None:
        await self._advance_time()
        number = index + 1
        self._line_no, self._line_text = number, block.strip()
        if self._events.has_subscribers:
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
        self._blocks_run += 1
        if self.time_scale <= 0 and self._blocks_run % 64 == 0:
            await asyncio.sleep(0)  # let abort / front-ends in (a polling loop too)
        self._events.hold()

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
        self._events.emit(ev)


def _store_of(truth: TruthModel) -> KinematicsStore | None:
    section = truth.machine_file.controller_kinematics
    if section is None:
        return None
    return KinematicsStore.from_spec(controller_kinematics(section, truth.machine))
