"""Exact forward kinematics of a five-axis serial chain with ISO 230-1 location and motion errors.

Conventions (METHOD.md §2, thesis Eqs 3.1-3.4): a topology string such as ``WCBXFZYT`` is read
workpiece to tool; every axis frame is an HTM in which the joint value enters directly (linear:
translation by +q along the axis direction; rotary: rotation by +q about it, right-hand rule).
Location (link) errors act in the parent frame just before the axis motion, in the order
``Trans(e) · Rot_x · Rot_y · Rot_z`` (METHOD.md table); motion (component) errors, used by the
simulator and the gap diagnosis, act just after the motion. All lengths in mm, angles in rad.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np

LINEAR_LETTERS = "XYZ"
ROTARY_LETTERS = "ABC"
# Principal direction index of each axis letter (X/A → x, Y/B → y, Z/C → z).
_AXIS_INDEX = {"X": 0, "Y": 1, "Z": 2, "A": 0, "B": 1, "C": 2}
_TRANS_NAMES = "XYZ"
_ROT_NAMES = "ABC"

# A nutating axis is commonly 45° (up to 50° on some heads) from its letter's direction.
MAX_INCLINATION_DEG = 60.0

MotionErrorFn = Callable[[np.ndarray], np.ndarray]
"""Maps joint values (N,) in model units to (N, 6) errors [EX, EY, EZ, EA, EB, EC] (mm, rad)."""


class TopologyError(ValueError):
    """The topology string or axis definitions do not describe a 3-linear + 2-rotary chain."""


@dataclass(frozen=True)
class Axis:
    """One machine axis. ``direction`` is a unit vector in the parent frame: principal on
    orthogonal machines, inclined on a nutating axis (e.g. B tilted 45° about X)."""

    letter: str
    kind: str  # "linear" | "rotary"
    direction: tuple[float, float, float]
    point_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)  # a point of a rotary axis line
    travel: tuple[float, float] = (-1e9, 1e9)  # controller units: mm or deg
    sign: int = 1  # model joint value = sign * controller value

    @property
    def index(self) -> int:
        """Index (0, 1, 2) of the principal direction the axis is named after (B → y): its own
        letter decides, so a 45° nutating B is still the y-type axis of ISO 230-1."""
        if self.letter in _AXIS_INDEX:
            return _AXIS_INDEX[self.letter]
        return int(np.argmax(np.abs(self.direction)))

    @property
    def inclined(self) -> bool:
        """Does the nominal direction leave the principal direction of the letter?"""
        return axis_frame(self) is not None

    def location_error_names(self) -> list[str]:
        """ISO 230-1 location errors of this axis: two tilts (+ two offsets if rotary)."""
        others = [i for i in range(3) if i != self.index]
        names = []
        if self.kind == "rotary":
            names += [f"E{_TRANS_NAMES[i]}0{self.letter}" for i in others]
        names += [f"E{_ROT_NAMES[i]}0{self.letter}" for i in others]
        return names


@dataclass(frozen=True)
class Machine:
    """A machine: topology, axes and nominal stylus tip (in the last tool frame, mm)."""

    name: str
    topology: str
    axes: Mapping[str, Axis]
    tool_tip_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    spindle_axis: tuple[float, float, float] = (0.0, 0.0, 1.0)  # from tip towards spindle
    # Location errors (ISO name, mm / rad) the CONTROLLER's kinematic model already holds after
    # a compensation: identification runs relative to them (``model.predict``); ``frames`` does
    # not apply them (they are the controller's belief, not the machine's physics).
    held_links: tuple[tuple[str, float], ...] = ()
    workpiece_chain: tuple[str, ...] = field(init=False)
    tool_chain: tuple[str, ...] = field(init=False)

    def __post_init__(self) -> None:
        wp, tl = parse_topology(self.topology)
        object.__setattr__(self, "workpiece_chain", wp)
        object.__setattr__(self, "tool_chain", tl)
        missing = [a for a in wp + tl if a not in self.axes]
        if missing:
            raise TopologyError(f"axes {missing} of topology {self.topology} are not defined")
        for letter in wp + tl:
            ax = self.axes[letter]
            want = "linear" if letter in LINEAR_LETTERS else "rotary"
            if ax.kind != want:
                raise TopologyError(f"axis {letter} must be {want}, got {ax.kind}")
            d = np.asarray(ax.direction, float)
            if not np.isclose(np.linalg.norm(d), 1.0):
                raise TopologyError(f"axis {letter}: direction {ax.direction} must be a unit "
                                    "vector")
            # An inclined axis keeps the ISO 230-1 names of its letter in its own frame (see
            # ``axis_frame``): it must stay within MAX_INCLINATION_DEG of the letter's direction.
            cos_min = np.cos(np.deg2rad(MAX_INCLINATION_DEG))
            if abs(d[_AXIS_INDEX[letter]]) < cos_min - 1e-12:
                raise TopologyError(
                    f"axis {letter}: direction {ax.direction} is more than "
                    f"{MAX_INCLINATION_DEG:g}° from {'xyz'[_AXIS_INDEX[letter]]} (ISO 230-1 names "
                    f"of {letter} refer to its {'xyz'[_AXIS_INDEX[letter]]} direction)"
                )
        known = self.location_error_names()
        for name, value in self.held_links:
            if name not in known:
                raise TopologyError(f"held link {name!r} is not a location error of "
                                    f"{self.topology} (known: {known})")
            if not np.isfinite(value):
                raise TopologyError(f"held link {name}: value {value} is not finite")

    def held_link_values(self) -> dict[str, float]:
        """The controller-held location errors by ISO name (repeated names summed)."""
        out: dict[str, float] = {}
        for name, value in self.held_links:
            out[name] = out.get(name, 0.0) + float(value)
        return out

    @property
    def linear_axes(self) -> list[str]:
        return [a for a in self.workpiece_chain + self.tool_chain if a in LINEAR_LETTERS]

    @property
    def rotary_axes(self) -> list[str]:
        """Rotary axes in alphabetical order: the first is the log's ``b``, the second ``c``."""
        return sorted(a for a in self.workpiece_chain + self.tool_chain if a in ROTARY_LETTERS)

    def location_error_names(self) -> list[str]:
        """Every candidate location error, rotary axes first (see ``identifiable_links``)."""
        chain = self.workpiece_chain + self.tool_chain
        rot = [n for a in chain if a in ROTARY_LETTERS for n in self.axes[a].location_error_names()]
        lin_tool = [n for a in self.tool_chain if a in LINEAR_LETTERS
                    for n in self.axes[a].location_error_names()]
        lin_wp = [n for a in self.workpiece_chain if a in LINEAR_LETTERS
                  for n in self.axes[a].location_error_names()]
        return rot + lin_tool + lin_wp


def parse_topology(topology: str) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """Split e.g. ``WCBXFZYT`` into the workpiece chain from F outward (X, B, C) and the tool
    chain from F to T (Z, Y). Case is ignored (seed 001 writes ``wBZfXYCt``)."""
    t = topology.upper()
    if len(t) != 8 or t[0] != "W" or t[-1] != "T" or t.count("F") != 1:
        raise TopologyError(
            f"topology {topology!r}: expected 8 letters 'W…F…T' (workpiece, foundation, tool) "
            "with 3 linear and 2 rotary axes, e.g. WCBXFZYT"
        )
    body = t[1:-1].replace("F", "")
    if sorted(body) != sorted(set(body)) or not set(body) <= set(LINEAR_LETTERS + ROTARY_LETTERS):
        raise TopologyError(f"topology {topology!r}: axis letters must be distinct X Y Z A B C")
    if sum(c in LINEAR_LETTERS for c in body) != 3 or sum(c in ROTARY_LETTERS for c in body) != 2:
        raise TopologyError(f"topology {topology!r}: needs exactly 3 linear and 2 rotary axes")
    f = t.index("F")
    return tuple(reversed(t[1:f])), tuple(t[f + 1 : -1])


# ---------------------------------------------------------------- elementary HTMs, batched


def _rot(index: int, angle: np.ndarray) -> np.ndarray:
    """Exact rotation HTMs about principal axis ``index``, batched over ``angle`` (N,)."""
    n = angle.shape[0]
    c, s = np.cos(angle), np.sin(angle)
    m = np.zeros((n, 4, 4))
    m[:, 3, 3] = 1.0
    i, j = [(1, 2), (2, 0), (0, 1)][index]
    m[:, index, index] = 1.0
    m[:, i, i] = c
    m[:, j, j] = c
    m[:, i, j] = -s
    m[:, j, i] = s
    return m


def _trans(v: np.ndarray) -> np.ndarray:
    """Translation HTMs, batched over v (N, 3)."""
    m = np.broadcast_to(np.eye(4), (v.shape[0], 4, 4)).copy()
    m[:, :3, 3] = v
    return m


def _small_htm(e: np.ndarray) -> np.ndarray:
    """Exact HTM ``Trans(ex,ey,ez) · Rot_x(ea) · Rot_y(eb) · Rot_z(ec)`` from (N, 6) errors."""
    m = _trans(e[:, :3])
    for k in range(3):
        if np.any(e[:, 3 + k]):
            m = m @ _rot(k, e[:, 3 + k])
    return m


@functools.lru_cache(maxsize=64)
def _location_slots(axis: Axis) -> tuple[tuple[str, int], ...]:
    """(ISO name, slot in [ex, ey, ez, ea, eb, ec]) of the axis' location errors (cached: this
    runs for every axis of every chain evaluation)."""
    out = []
    for name in axis.location_error_names():
        c = name[1]  # EX0C → translation along x; EA0C → rotation about x
        out.append((name, _TRANS_NAMES.index(c) if c in _TRANS_NAMES else 3 + _ROT_NAMES.index(c)))
    return tuple(out)


@functools.lru_cache(maxsize=64)
def axis_frame(axis: Axis) -> np.ndarray | None:
    """Rotation R0 (3, 3) taking the letter's signed principal direction onto an inclined axis'
    direction (the smallest such rotation, Rodrigues), or None for a principal axis.

    An inclined axis' location errors are defined in the frame R0 carries the parent frame to
   : EX0B of a B tilted 45° about X is the offset of the B line along R0·x, EA0B its
    tilt about R0·x, and so on — the ISO 230-1 names of a principal B in the axis' own frame.
    On a principal axis R0 is the identity and nothing changes."""
    d = np.asarray(axis.direction, float)
    d = d / np.linalg.norm(d)
    e = np.zeros(3)
    e[axis.index] = 1.0 if d[axis.index] >= 0 else -1.0
    v = np.cross(e, d)
    s, c = float(np.linalg.norm(v)), float(e @ d)
    if s < 1e-12:
        return None
    k = v / s
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + s * kx + (1.0 - c) * (kx @ kx)


def _conjugate(r0: np.ndarray, m: np.ndarray) -> np.ndarray:
    """R0 · m · R0ᵀ for batched HTMs m (N, 4, 4): a motion given in the axis frame."""
    h = np.eye(4)
    h[:3, :3] = r0
    return h @ m @ h.T


def _location_htm(axis: Axis, links: Mapping[str, float]) -> np.ndarray | None:
    """(1, 4, 4) the axis' location errors (the same for every pose: broadcast by ``@``)."""
    e = np.zeros(6)
    for name, slot in _location_slots(axis):
        v = links.get(name, 0.0)
        if v:
            e[slot] = v
    if not e.any():
        return None
    m = _small_htm(e[None, :])
    r0 = axis_frame(axis)
    return m if r0 is None else _conjugate(r0, m)


def axis_htm(
    axis: Axis,
    q: np.ndarray,
    links: Mapping[str, float] | None = None,
    motion_error: MotionErrorFn | None = None,
) -> np.ndarray:
    """Parent→axis HTM for joint values ``q`` (N,) in model units (mm or rad)."""
    n = q.shape[0]
    d = np.asarray(axis.direction, float)
    r0 = axis_frame(axis)
    if axis.kind == "linear":
        m = _trans(q[:, None] * d[None, :])
    else:
        sgn = 1.0 if d[axis.index] >= 0 else -1.0  # an axis along -z turns by -q about +z
        m = _rot(axis.index, sgn * q)
        if r0 is not None:  # about the inclined direction: R0 · Rot(q) · R0ᵀ
            m = _conjugate(r0, m)
        p = np.asarray(axis.point_mm, float)
        if p.any():
            m = _trans(p[None, :]) @ m @ _trans(-p[None, :])
    if links:
        loc = _location_htm(axis, links)
        if loc is not None:
            m = loc @ m
    if motion_error is not None:
        em = _small_htm(np.asarray(motion_error(q), float).reshape(n, 6))
        m = m @ (em if r0 is None else _conjugate(r0, em))
    return m


@dataclass
class ChainState:
    """Everything the chain needs beyond joint values: errors and setup."""

    links: Mapping[str, float] = field(default_factory=dict)  # ISO name → mm / rad
    tip_offset_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))  # last tool frame
    linear_scale: float = 0.0  # isotropic scale of the linear axes (dimensionless)
    motion_errors: Mapping[str, MotionErrorFn] = field(default_factory=dict)


def to_model(machine: Machine, q_ctrl: Mapping[str, np.ndarray], scale: float = 0.0) -> dict:
    """Controller values (mm, deg) → model joint values (mm, rad), sign and scale applied."""
    out = {}
    for letter, v in q_ctrl.items():
        ax = machine.axes[letter]
        v = np.asarray(v, float) * ax.sign
        out[letter] = v * (1.0 + scale) if ax.kind == "linear" else np.deg2rad(v)
    return out


def frames(
    machine: Machine, q_model: Mapping[str, np.ndarray], state: ChainState
) -> tuple[np.ndarray, np.ndarray]:
    """Return (F_T_W, F_T_T) batched HTMs (N, 4, 4) for model joint values."""
    n = np.asarray(next(iter(q_model.values()))).shape[0]

    def branch(chain: tuple[str, ...]) -> np.ndarray:
        m = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
        for letter in chain:
            q = np.asarray(q_model[letter], float)
            m = m @ axis_htm(machine.axes[letter], q, state.links,
                             state.motion_errors.get(letter))
        return m

    f_w = branch(machine.workpiece_chain)
    f_t = branch(machine.tool_chain)
    return f_w, f_t


def tip_minus_ball(
    machine: Machine,
    q_model: Mapping[str, np.ndarray],
    ball_mm: np.ndarray,
    state: ChainState,
) -> np.ndarray:
    """Stylus-tip centre minus ball centre in the foundation frame (N, 3), mm.

    ``ball_mm`` (N, 3) is each ball centre in the last workpiece frame (nominal + setup error);
    the tip is the nominal tool tip + ``state.tip_offset_mm`` in the last tool frame (Eq. 3.1).
    """
    f_w, f_t = frames(machine, q_model, state)
    tip = np.asarray(machine.tool_tip_mm, float) + state.tip_offset_mm
    tip_f = f_t[:, :3, :3] @ np.broadcast_to(tip, ball_mm.shape)[..., None]
    tip_f = tip_f[..., 0] + f_t[:, :3, 3]
    ball_f = (f_w[:, :3, :3] @ ball_mm[..., None])[..., 0] + f_w[:, :3, 3]
    return tip_f - ball_f


def solve_centre(
    machine: Machine,
    rotary_ctrl: Mapping[str, np.ndarray],
    ball_mm: np.ndarray,
    state: ChainState,
    guess_ctrl: np.ndarray | None = None,
    tol_mm: float = 1e-11,
    max_iter: int = 20,
) -> np.ndarray:
    """Controller linear-axis values (N, 3; columns X, Y, Z) that put the tip on the ball centre.

    Without motion errors the tip-ball vector is affine in the linear joints for fixed rotary
    joints, so the finite-difference Jacobian with a 1 mm step is exact and one Newton step
    converges; with position-dependent motion errors a few more steps are taken.
    """
    n = ball_mm.shape[0]
    q_lin = np.zeros((n, 3)) if guess_ctrl is None else np.array(guess_ctrl, float)
    rot_model = to_model(machine, rotary_ctrl)

    def g(qc: np.ndarray) -> np.ndarray:
        qm = to_model(machine, {k: qc[:, i] for i, k in enumerate("XYZ")}, state.linear_scale)
        return tip_minus_ball(machine, {**qm, **rot_model}, ball_mm, state)

    for _ in range(max_iter):
        g0 = g(q_lin)
        jac = np.empty((n, 3, 3))
        for k in range(3):
            dq = q_lin.copy()
            dq[:, k] += 1.0
            jac[:, :, k] = g(dq) - g0
        step = np.linalg.solve(jac, -g0[..., None])[..., 0]
        q_lin = q_lin + step
        if np.max(np.abs(step)) < tol_mm:
            break
    return q_lin


def rotary_columns(machine: Machine, b_deg: np.ndarray, c_deg: np.ndarray) -> dict:
    """Map the log's ``b``/``c`` columns onto the machine's rotary axis letters."""
    first, second = machine.rotary_axes
    return {first: np.asarray(b_deg, float), second: np.asarray(c_deg, float)}
