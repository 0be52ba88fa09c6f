"""The five touch directions in the tool frame: the pole against the spindle, the
four equator touches the machine X-Y diagonals (``contracts.messages.TOUCH_DIRECTIONS``) carried
by the smallest rotation from z onto the spindle direction, optionally turned about it."""

from __future__ import annotations

import math

import numpy as np

from contracts.messages import TOUCH_DIRECTIONS

# Turns of the equator square about the spindle a tilted-probe program may use (programs.tilted:
# the first whose path is clear of the rods); the simulator's latch recognises them all.
EQUATOR_TURNS_DEG = (0.0, 22.5, 45.0, 67.5)


def rotation_z_to(s: np.ndarray) -> np.ndarray:
    """Smallest rotation taking +z onto the unit vector s (Rodrigues; identity for s = z)."""
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(z, s)
    sn, c = float(np.linalg.norm(v)), float(z @ s)
    if sn < 1e-12:
        if c > 0:
            return np.eye(3)
        return np.diag([1.0, -1.0, -1.0])  # spindle pointing up: half turn about x
    k = v / sn
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + sn * kx + (1.0 - c) * (kx @ kx)


def equator_directions(spindle: np.ndarray, turn_deg: float = 0.0) -> dict[int, np.ndarray]:
    """Touch directions 1-5 (tool relative to workpiece, foundation frame) at a unit spindle
    direction (tip → spindle); with s = z and no turn they are ``TOUCH_DIRECTIONS``."""
    rz = rotation_z_to(spindle)
    t = math.radians(turn_deg)
    turn = np.array([[math.cos(t), -math.sin(t), 0.0], [math.sin(t), math.cos(t), 0.0],
                     [0.0, 0.0, 1.0]])
    out = {tt: rz @ turn @ np.asarray(TOUCH_DIRECTIONS[tt], float) for tt in (1, 2, 3, 4)}
    out[5] = -np.asarray(spindle, float)
    return out
