"""The virtual CNC's machine side (the interpreter's MachineIO): axes, motion time, probing."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from contracts.result_lines import RING_SLOTS
from simulators.controller_events import ControllerEvent, FaultEvent, PrintLine, TouchResult
from simulators.faults import FaultPlan
from simulators.gcode import Alarm, ProbeOutcome
from simulators.latch import Latch, ProbeLatch, TouchRecord
from simulators.motion import check_travel, move_time_s, probing_length_mm
from simulators.probe import collision
from simulators.truth import TruthModel


class MachineSide:
    """What the G-code interpreter drives on ``VirtualController``: position, moves with their
    machine time, dwell, output lines, operator messages and probing touches on the truth."""

    truth: TruthModel
    faults: FaultPlan
    axes: tuple[str, ...]
    machine_time_s: float
    _warm_s: float  # the thermal clock at the program's start (VirtualController.thermal_time_s)
    printed: list[str]
    print_files: dict[str, list[str]]
    messages: list[str]
    touches: list[TouchRecord]
    _pos: dict[str, float]
    _pending_s: float
    _latch: ProbeLatch
    _rotary_moves: int
    _drop_lines: int
    _seq: int

    def _emit(self, ev: ControllerEvent) -> None:
        raise NotImplementedError

    def position(self) -> dict[str, float]:
        return dict(self._pos)

    def _q(self, pos: dict[str, float]) -> np.ndarray:
        return np.array([pos[a] for a in self.axes], float)

    def move(self, target: dict[str, float], feed_mm_min: float | None) -> None:
        check_travel(self.truth.machine, self.axes, target)
        q0, q1 = self._q(self._pos), self._q(target)
        hit = collision(self.truth, q0, q1, self.machine_time_s + self._pending_s)
        if hit:
            raise Alarm(f"PROBE COLLISION: {hit} on the move to "
                        + " ".join(f"{a}{target[a]:.4f}" for a in self.axes))
        dt, indexed = move_time_s(self.truth.machine_file.dynamics, q0, q1, feed_mm_min)
        self._rotary_moves += int(indexed)  # the visit key of the probing noise counts these
        self._pending_s += dt
        self._pos = dict(target)

    def dwell(self, seconds: float) -> None:
        if seconds < 0:
            raise Alarm("negative dwell")
        self._pending_s += seconds

    def output(self, text: str, target: str | None = None) -> None:
        """A printed line (DPRNT, WRITE, FN 16, LOG) on the DNC line; ``target``: the file it
        also goes to (FN 16's output file, kept by name in ``print_files``)."""
        if self._drop_lines > 0:
            self._drop_lines -= 1
            return
        self.printed.append(text)
        if target is not None:
            name = target.split("\\")[-1].split("/")[-1].upper()
            self.print_files.setdefault(name, []).append(text)
        self._emit(PrintLine(text))

    def message(self, text: str) -> None:
        self.messages.append(text)

    def _probing_length(self, target: dict[str, float], feed_mm_min: float) -> float:
        """Length of a probing move from here to ``target`` (rotary motion counted too)."""
        b, c = self._pos[self.axes[3]], self._pos[self.axes[4]]
        return probing_length_mm(self.truth.machine_file.dynamics, self._q(self._pos)[:3],
                                 self._q(target)[:3],
                                 target[self.axes[3]] != b or target[self.axes[4]] != c,
                                 feed_mm_min)

    def _stop_at(self, hit: Latch, length: float, feed_mm_min: float) -> dict[str, float]:
        """The probing move ends where the stylus stopped: its machine time and position;
        returns the latched axis values."""
        self._pending_s += length * (hit.fraction if hit.fraction is not None else 1.0) \
            / feed_mm_min * 60
        b, c = self._pos[self.axes[3]], self._pos[self.axes[4]]
        self._pos.update({"X": hit.stop[0], "Y": hit.stop[1], "Z": hit.stop[2]})
        return {"X": float(hit.xyz[0]), "Y": float(hit.xyz[1]), "Z": float(hit.xyz[2]),
                self.axes[3]: b, self.axes[4]: c}

    def probe(self, target: dict[str, float], feed_mm_min: float, locate: bool = False
              ) -> ProbeOutcome:
        check_travel(self.truth.machine, self.axes, target)
        if locate:
            return self._locate(target, feed_mm_min)
        self._seq += 1
        seq = self._seq
        t = self.machine_time_s + self._pending_s
        p0, p1 = self._q(self._pos)[:3], self._q(target)[:3]
        b, c = self._pos[self.axes[3]], self._pos[self.axes[4]]
        length = self._probing_length(target, feed_mm_min)
        faults = self.faults.due({"no_trigger", "early_trigger", "drop_result_line", "chip"},
                                 touch=seq, t_s=t)
        for f in faults:
            self._emit(FaultEvent(f.kind, f))
            if f.kind == "drop_result_line":
                self._drop_lines += f.params.get("lines", 1)
        hit = self._latch.latch(p0, p1, b, c, t, faults, self._rotary_moves, feed_mm_min,
                                thermal_t_s=self._warm_s + t)
        if hit.triggered and hit.target is not None and hit.target >= 0:
            chip = self.faults.chip_mm(faults, hit.ball, hit.touch, b, c, seq)
            if chip:  # a chip on the ball: the stylus meets it that much earlier on the line
                back = (p1 - p0) / hit.length_mm * chip
                hit = replace(hit, fraction=hit.fraction - chip / hit.length_mm,
                              stop=hit.stop - back, xyz=hit.xyz - back)
        latched = self._stop_at(hit, length, feed_mm_min)
        self.touches.append(TouchRecord(seq, t, p0, p1, latched, hit.triggered, feed_mm_min,
                                        hit.touch, hit.direction, hit.ball, hit.target))
        self._emit(TouchResult((seq - 1) % RING_SLOTS, seq,
                               {"X": latched["X"], "Y": latched["Y"], "Z": latched["Z"],
                                "b": b, "c": c}, hit.triggered))
        return ProbeOutcome(hit.triggered, latched)

    def _locate(self, target: dict[str, float], feed_mm_min: float) -> ProbeOutcome:
        """The fast approach of a two-speed touch: probe physics and machine time, but no
        touch number, result or probing fault (the re-touch that follows is the touch)."""
        p0, p1 = self._q(self._pos)[:3], self._q(target)[:3]
        b, c = self._pos[self.axes[3]], self._pos[self.axes[4]]
        length = self._probing_length(target, feed_mm_min)
        t = self.machine_time_s + self._pending_s
        hit = self._latch.latch(p0, p1, b, c, t, [], self._rotary_moves, feed_mm_min,
                                locate=True)
        return ProbeOutcome(hit.triggered, self._stop_at(hit, length, feed_mm_min))
