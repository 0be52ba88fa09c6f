"""Offline run: execute one program on the virtual controller and turn its touches into the
probing-log rows of DESIGN.md (the ``rumba sim --run`` path, also used by tests and benchmarks).

Identity of a touch (repeat, pose, ball, touch) comes from the program's own result lines
(``RUMBA seq rep pose ball touch trig …``, gcode_templates/README.md) matched by sequence number;
a program without them gets it inferred: pose = order of first appearance of a (b, c)
indexation, ball = the ball whose nominal centre the move aims at, touch = from the direction.
Positions are the controller's latched registers at full precision (the printed lines are
rounded to the dialect's decimals).
"""

from __future__ import annotations

import asyncio
import time
import tracemalloc
from dataclasses import dataclass
from pathlib import Path

from contracts.messages import TOUCH_DIRECTIONS
from contracts.probing_log import LogRow
from simulators.controller import VirtualController
from simulators.faults import FaultPlan
from simulators.truth import TruthModel


@dataclass
class OfflineResult:
    controller: VirtualController
    rows: list[LogRow]
    state: str
    alarm: str | None
    machine_time_s: float
    wall_s: float
    peak_memory_mb: float | None = None


def _identity_from_lines(lines: list[str]) -> dict[int, tuple[int, int, str, int]]:
    out = {}
    for line in lines:
        f = line.split()
        if len(f) >= 6 and f[0] == "RUMBA":
            try:
                out[int(f[1])] = (int(f[2]), int(f[3]), f[4], int(f[5]))
            except ValueError:
                continue
    return out


def touches_to_rows(vc: VirtualController, run_id: str) -> list[LogRow]:
    """Probing-log rows of every triggered touch of the last program."""
    ids = _identity_from_lines(vc.printed)
    truth = vc.truth
    r1, r2 = truth.rotary_letters
    poses: dict[tuple[float, float], int] = {}
    seen: dict[tuple[int, str, int], int] = {}
    rows = []
    for t in vc.touches:
        b, c = t.latched[r1], t.latched[r2]
        key = (round(b, 6), round(c, 6))
        poses.setdefault(key, len(poses))
        direction = t.direction
        if t.seq in ids:
            rep, pose, ball, touch = ids[t.seq]
            # As the daemon logs it (contracts/touch_table.py): the program's direction of that
            # touch, the one the latch recognised (a tilted touch's in the tool frame).
            direction = t.direction if touch == t.touch else TOUCH_DIRECTIONS.get(touch,
                                                                                  t.direction)
        else:
            pose, ball, touch = poses[key], truth.artefact.ids[t.ball], t.touch
            rep = seen.get((pose, ball, touch), 0)
            seen[(pose, ball, touch)] = rep + 1
        if not t.triggered or touch not in range(1, 6):
            continue
        rows.append(LogRow(run_id, t.seq, round(t.t_s, 3), rep, pose, b, c, ball, touch,
                           *direction, t.latched["X"], t.latched["Y"], t.latched["Z"],
                           b, c, t.feed_mm_min))
    return rows


async def run_program(truth: TruthModel, text: str, dialect: str, *,
                      files: dict[str, str] | None = None, seed: int = 0,
                      time_scale: float = 0.0, faults: FaultPlan | None = None,
                      run_id: str = "sim", timeout_s: float | None = None,
                      measure_memory: bool = False) -> OfflineResult:
    """Load, start and wait for one program; return the controller and the log rows."""
    if measure_memory:
        tracemalloc.start()
    t0 = time.perf_counter()
    vc = VirtualController(truth, time_scale=time_scale, rng_seed=seed, faults=faults,
                           dialect=dialect)
    await vc.load_program(text, dialect, files)
    await vc.start()
    state = await vc.wait_done(timeout_s)
    wall = time.perf_counter() - t0
    peak = None
    if measure_memory:
        peak = tracemalloc.get_traced_memory()[1] / 2**20
        tracemalloc.stop()
    return OfflineResult(vc, touches_to_rows(vc, run_id), state, vc.alarm, vc.machine_time_s,
                         wall, peak)


MAX_AUX_BYTES = 1 << 20  # an F-PRINT format file is a few lines
MAX_AUX_FILES = 32


def aux_files(program: Path, error: type[Exception] = ValueError) -> dict[str, str]:
    """Files that travel with a program: Heidenhain F-PRINT format files (``*.A``) beside it;
    regular files only (a FIFO or device named ``*.A`` is no format file), each bounded and
    UTF-8, else one ``error`` line naming the file."""
    from contracts.input_files import read_bounded

    names = [p for p in sorted(program.parent.glob("*.A")) if p.is_file()]
    if len(names) > MAX_AUX_FILES:
        raise error(f"{program.parent}: {len(names)} *.A files beside {program.name}: more "
                    f"than {MAX_AUX_FILES} format files travel with no program")
    out = {}
    for p in names:
        raw = read_bounded(p, error, MAX_AUX_BYTES, "Heidenhain format file")
        try:
            out[p.name] = raw.decode("utf-8")
        except UnicodeDecodeError as e:
            raise error(f"{p}: byte {e.start}: not UTF-8 text") from None
    return out


def run_sync(*args, **kw) -> OfflineResult:
    return asyncio.run(run_program(*args, **kw))
