"""Messages shared by drivers, the simulator and the daemon (dataclasses, no behaviour)."""

from __future__ import annotations

from dataclasses import dataclass, field

TOUCH_DIRECTIONS: dict[int, tuple[float, float, float]] = {
    # Nominal approach direction of the tool relative to the workpiece, machine frame
    # (METHOD.md §1): four equator diagonals in the X-Y plane, then the pole along the spindle.
    1: (0.7071067811865476, 0.7071067811865476, 0.0),
    2: (-0.7071067811865476, 0.7071067811865476, 0.0),
    3: (-0.7071067811865476, -0.7071067811865476, 0.0),
    4: (0.7071067811865476, -0.7071067811865476, 0.0),
    5: (0.0, 0.0, -1.0),
}
"""Touch 5 is the pole, approached against the spindle axis (here +Z, so along -Z); a machine
with another spindle axis gets its own pole direction from ``programs.toolpath``."""


@dataclass(frozen=True)
class TouchId:
    """Stable identity of one touch, carried through the program into its result."""

    seq: int  # 1-based running number in the program
    pose: int  # 0-based pose index in the plan
    ball: str  # ball id (safe name)
    touch: int  # 1..4 equator diagonals, 5 pole
    repeat: int = 0


@dataclass(frozen=True)
class ProbeHit:
    """One latched probe result as it arrives from the controller."""

    seq: int
    pose: int
    ball: str
    touch: int
    axes: dict[str, float]  # latched controller values: X Y Z mm, rotary (b/c letters) deg
    triggered: bool
    t_s: float = 0.0  # seconds since the run's first program started, whichever program of the
    # run (a re-probe round's too) it comes from: contracts.jobs.RunClock; 0: not stamped yet
    repeat: int = 0
    raw: str = ""  # the line / registers it was decoded from, kept for the journal
    b_cmd_deg: float = 0.0
    c_cmd_deg: float = 0.0
    direction: tuple[float, float, float] = (0.0, 0.0, 0.0)
    feed_mm_min: float = 0.0
    extra: dict[str, float] = field(default_factory=dict)
