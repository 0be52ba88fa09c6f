"""How the axes of the simulated machine move: travel limits, move times, probing-move rules."""

from __future__ import annotations

import numpy as np

from contracts.setup_files import DynamicsFile
from identification.kinematics import Machine
from simulators.gcode import Alarm


def check_travel(machine: Machine, axes: tuple[str, ...], target: dict[str, float]) -> None:
    """Alarm when ``target`` leaves the travel of any axis (1 nm tolerance for rounding)."""
    for a in axes:
        lo, hi = machine.axes[a].travel
        if not lo - 1e-9 <= target[a] <= hi + 1e-9:
            raise Alarm(f"OVERTRAVEL {a}{target[a]:+.4f} outside [{lo:g}, {hi:g}]")


def move_time_s(dyn: DynamicsFile, q0: np.ndarray, q1: np.ndarray, feed_mm_min: float | None
                ) -> tuple[float, bool]:
    """Machine time of the move q0 → q1 (X Y Z mm, then the rotary axes in deg), rapid when
    ``feed_mm_min`` is None, and whether it indexed a rotary axis."""
    lin = float(np.linalg.norm(q1[:3] - q0[:3]))
    rot = float(np.max(np.abs(q1[3:] - q0[3:])))
    if feed_mm_min is None:
        dt = max(np.max(np.abs(q1[:3] - q0[:3])) / dyn.rapid_mm_min,
                 rot / dyn.rotary_rapid_deg_min) * 60.0
    else:
        dt = (lin if lin > 0 else rot) / min(feed_mm_min, dyn.max_feed_mm_min) * 60.0
    if rot > 0:
        dt += dyn.rotary_clamp_s  # unclamp + clamp of the indexed axes
    return dt, rot > 0


def probing_length_mm(dyn: DynamicsFile, p0: np.ndarray, p1: np.ndarray, rotary_moved: bool,
                      feed_mm_min: float) -> float:
    """Length of a probing move p0 → p1 (X Y Z); alarm on what a control refuses: a feed above
    the machine's probing limit, rotary axes moving, a move of zero length."""
    if feed_mm_min > dyn.max_probe_feed_mm_min:
        raise Alarm(f"probing feed F{feed_mm_min:g} above the machine's limit "
                    f"{dyn.max_probe_feed_mm_min:g}")
    if rotary_moved:
        raise Alarm("rotary axes must not move during a probing move")
    length = float(np.linalg.norm(p1 - p0))
    if length <= 0:
        raise Alarm("probing move of zero length")
    return length
