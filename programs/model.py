"""The data of a probing program: targets, touches, moves and the program they make up."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from contracts.input_files import read_bounded
from contracts.messages import TouchId
from contracts.setup_files import MachineFile, Plan
from contracts.touch_table import TouchInfo, TouchTable
from contracts.yaml_files import ConfigError
from identification.kinematics import ChainState, Machine
from identification.model import Artefact

MAX_TARGETS_BYTES = 16 * 2**20
"""Ceiling on a targets file (a `rumba analyze --json` file is well under 1 MB)."""


@dataclass(frozen=True)
class Targets:
    """Where the balls and the stylus really are: nominal, or the last run's setup estimate."""

    source: str = "nominal"  # "nominal" | "estimate"
    ball_offsets_mm: Mapping[str, tuple[float, float, float]] = field(default_factory=dict)
    tip_offset_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)


def load_targets(path: Path | str, artefact: Artefact) -> Targets:
    """Read ``setup.balls.<id>.value`` and ``setup.probe.value`` (µm, as `rumba analyze --json`)."""
    # a regular file of bounded size: a FIFO would block, /dev/zero never end
    raw = read_bounded(path, ConfigError, MAX_TARGETS_BYTES, "`rumba analyze --json` file")
    try:
        data = json.loads(raw.decode("utf-8"))
    except UnicodeDecodeError as e:
        raise ConfigError(f"{path}: byte {e.start}: not UTF-8 text") from None
    except json.JSONDecodeError as e:
        raise ConfigError(f"{path}: line {e.lineno}: not valid JSON: {e.msg}") from None
    except RecursionError:
        raise ConfigError(f"{path}: nested too deeply: not a `rumba analyze --json` "
                          "file") from None

    def vec(node: object, key: str) -> tuple[float, float, float]:
        v = node.get("value") if isinstance(node, dict) else None
        if (not isinstance(v, list) or len(v) != 3
                or not all(isinstance(x, int | float) and math.isfinite(x) for x in v)):
            raise ConfigError(f"{path}: {key}.value: expected 3 finite numbers (µm)")
        if max(abs(x) for x in v) > 5000:
            raise ConfigError(f"{path}: {key}.value: {v} µm is beyond 5 mm: not a setup error")
        return (v[0] / 1000.0, v[1] / 1000.0, v[2] / 1000.0)

    setup = data.get("setup") if isinstance(data, dict) else None
    if not isinstance(setup, dict) or not isinstance(setup.get("balls"), dict):
        raise ConfigError(f"{path}: setup.balls: missing (expected the JSON of `rumba analyze`)")
    balls = setup["balls"]
    missing = [b for b in artefact.ids if b not in balls]
    if missing:
        raise ConfigError(f"{path}: setup.balls: no estimate for balls {missing}")
    offsets = {b: vec(balls[b], f"setup.balls.{b}") for b in artefact.ids}
    tip = vec(setup.get("probe"), "setup.probe")
    return Targets("estimate", offsets, tip)


@dataclass(frozen=True)
class Touch:
    """One touch: identity, intended relative direction and its controller points (X, Y, Z)."""

    id: TouchId
    ball_number: int  # 1-based, artefact file order
    direction: tuple[float, float, float]  # tool relative to workpiece, machine frame
    b_deg: float
    c_deg: float
    centre: tuple[float, float, float]  # controller X Y Z putting the tip on the ball centre
    start: tuple[float, float, float]
    contact: tuple[float, float, float]
    end: tuple[float, float, float]
    feed_mm_min: float


@dataclass(frozen=True)
class Move:
    """One block: ``target`` is the full controller state X Y Z r1 r2 after it; ``words`` are the
    programmed axes. Kinds: rapid; feed (linear at ``feed_mm_min``: to the start point, or a
    radial move whose dog-legs would not be clear); probe; retract (back out along a probing
    line: rapid, or linear when ``feed_mm_min`` > 0); dwell. A two-speed probe
    (``locate_feed_mm_min`` > 0) first locates the surface at that feed, backs off
    ``backoff_mm`` from the latched point along the line and re-touches at ``feed_mm_min``
    (the latched value), all on its probing line."""

    block: int
    kind: str
    target: tuple[float, float, float, float, float]
    words: tuple[str, ...]
    feed_mm_min: float = 0.0
    pose: int = -1
    ball: str = ""
    touch: Touch | None = None
    dwell_s: float = 0.0
    locate_feed_mm_min: float = 0.0
    backoff_mm: float = 0.0
    # A feed move whose straight line was checked (tilted-probe transits): a dialect
    # whose rapid is a straight line (``Dialect.linear_rapid``) renders it as a rapid
    linear_rapid: bool = False


@dataclass
class Program:
    """A generated program, dialect-free: the moves a dialect renders and safety simulates."""

    machine: Machine
    machine_file: MachineFile
    artefact: Artefact
    plan: Plan
    targets: Targets
    rotary: tuple[str, str]
    retract_axis: int  # index 0..2 of the controller linear axis along the spindle
    standoff_mm: float
    overtravel_mm: float
    moves: list[Move] = field(default_factory=list)
    touches: list[Touch] = field(default_factory=list)
    # the spindle tilts (a swivel or fork head): X Y Z command the head pivot with
    # TCPM and tool-length offset off, which every dialect states and sets (``tcpm_off``)
    tilted: bool = False
    # macro variables the program prints at its start, at each pose and at its end (
    # temperature channels over DNC, ``RTEMP`` lines); checked by the dialect before printing
    temperature_vars: tuple[str, ...] = ()
    # a link reads the results from the controller's variables (contracts.result_lines
    # HANDSHAKE_VARIABLES): before each probing move the program waits while the ring is full
    # and ends at the link's stop request
    handshake: bool = False

    @property
    def axis_letters(self) -> tuple[str, str, str, str, str]:
        return ("X", "Y", "Z", *self.rotary)

    @property
    def state(self) -> ChainState:
        return chain_state(self.targets)

    def ball_positions_mm(self) -> np.ndarray:
        """Ball centres in the last workpiece frame used as targets and keep-outs (mm)."""
        return ball_positions(self.artefact, self.targets)

    def touch_table(self) -> TouchTable:
        """The program's touch table: what names and completes every result of a run."""
        return TouchTable(TouchInfo(t.id, float(t.b_deg), float(t.c_deg),
                                    tuple(map(float, t.direction)), float(t.feed_mm_min))
                          for t in self.touches)


def chain_state(targets: Targets) -> ChainState:
    """The chain state the targets imply (the stylus tip offset of the setup estimate)."""
    return ChainState(tip_offset_mm=np.asarray(targets.tip_offset_mm, float))


def ball_positions(artefact: Artefact, targets: Targets) -> np.ndarray:
    """Ball centres (N, 3) in the last workpiece frame: nominal plus the targets' offsets."""
    off = np.array([targets.ball_offsets_mm.get(b.id, (0.0, 0.0, 0.0)) for b in artefact.balls])
    return artefact.nominal_mm + off


def plan_visits(plan: Plan) -> list[tuple[int, int]]:
    """(repeat, pose index) of every visit in run order: the poses ``repeats`` times, then —
    with ``drift_check`` — the first pose once more as the next repeat (its centres against
    the first visit's give the run's thermal stability)."""
    visits = [(rep, ip) for rep in range(plan.repeats) for ip in range(len(plan.poses))]
    if plan.drift_check:
        visits.append((plan.repeats, 0))
    return visits
