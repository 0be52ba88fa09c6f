"""The RUMBA measurement model: parameter layout and predicted ball centres with their Jacobian.

A measured centre is the controller X, Y, Z at which the stylus-tip centre sits on a ball centre
for a given B/C indexation (sphere fit of the five touches, METHOD.md §1). Its prediction solves
the exact chain (thesis Eq. 3.1) for those linear-axis values; the Jacobian follows from the
implicit-function theorem: dq/dp = -(dg/dq)^-1 dg/dp with g = tip - ball in the foundation frame.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from identification.kinematics import (
    Axis,
    ChainState,
    Machine,
    MotionErrorFn,
    axis_frame,
    axis_htm,
    frames,
    rotary_columns,
    tip_minus_ball,
    to_model,
)


@dataclass(frozen=True)
class Ball:
    """A master ball: nominal centre in the last workpiece frame (mm)."""

    id: str
    position_mm: tuple[float, float, float]
    diameter_mm: float = 25.4
    rod_length_mm: float = 100.0
    rod_diameter_mm: float = 8.0


@dataclass(frozen=True)
class CalibratedDistance:
    """A calibrated centre-to-centre distance between two balls (scale-enriched artefact)."""

    ball_a: str
    ball_b: str
    distance_mm: float
    std_um: float = 0.5


@dataclass(frozen=True)
class Artefact:
    name: str
    balls: tuple[Ball, ...]
    distances: tuple[CalibratedDistance, ...] = ()

    @property
    def ids(self) -> list[str]:
        return [b.id for b in self.balls]

    @property
    def nominal_mm(self) -> np.ndarray:
        return np.array([b.position_mm for b in self.balls], float)


@dataclass(frozen=True)
class Layout:
    """Order and meaning of the parameter vector: links, ball setups, probe setup, [scale].

    Internal units: mm and rad (and a dimensionless scale); reports convert to µm and µrad.
    """

    links: tuple[str, ...]
    n_balls: int
    scale: bool = False

    @property
    def size(self) -> int:
        return len(self.links) + 3 * self.n_balls + 3 + int(self.scale)

    @property
    def ball_slice(self) -> slice:
        k = len(self.links)
        return slice(k, k + 3 * self.n_balls)

    @property
    def tip_slice(self) -> slice:
        k = len(self.links) + 3 * self.n_balls
        return slice(k, k + 3)

    def names(self, ball_ids: Sequence[str]) -> list[str]:
        out = list(self.links)
        out += [f"ball {b} d{a}" for b in ball_ids for a in "xyz"]
        out += [f"probe d{a}" for a in "xyz"]
        if self.scale:
            out.append("isotropic scale")
        return out

    def unpack(self, p: np.ndarray) -> tuple[dict[str, float], np.ndarray, np.ndarray, float]:
        links = dict(zip(self.links, p[: len(self.links)], strict=True))
        balls = p[self.ball_slice].reshape(self.n_balls, 3)
        tip = p[self.tip_slice]
        scale = float(p[-1]) if self.scale else 0.0
        return links, balls, tip, scale


@dataclass
class Centres:
    """Ball centres per (pose, ball): measured (controller mm) and where they were measured."""

    pose: np.ndarray  # (K,) pose index
    ball: np.ndarray  # (K,) ball index into the artefact
    b_deg: np.ndarray  # (K,) first rotary axis, controller deg
    c_deg: np.ndarray  # (K,) second rotary axis, controller deg
    xyz_mm: np.ndarray  # (K, 3) measured centre, controller X Y Z
    t_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    # from touches (identification/spherefit.py ``centre_sensitivity``), else empty: each
    # touch's time (K, n) and d(centre)/d(touch point) (K, n, 3, 3), so that a drift moving
    # during a ball's touches reaches its centre as the fit carries it
    touch_t_s: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    touch_sens: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 3, 3)))

    def __len__(self) -> int:
        return int(self.pose.shape[0])

    def subset(self, mask: np.ndarray) -> Centres:
        t = self.t_s[mask] if self.t_s.size else self.t_s
        touched = len(self.touch_t_s) == len(self) and len(self) > 0
        return Centres(self.pose[mask], self.ball[mask], self.b_deg[mask], self.c_deg[mask],
                       self.xyz_mm[mask], t,
                       self.touch_t_s[mask] if touched else self.touch_t_s,
                       self.touch_sens[mask] if touched else self.touch_sens)


def _g(machine: Machine, rot_model: Mapping, balls_w: np.ndarray, q_ctrl: np.ndarray,
       state: ChainState) -> np.ndarray:
    qm = to_model(machine, {k: q_ctrl[:, i] for i, k in enumerate("XYZ")}, state.linear_scale)
    return tip_minus_ball(machine, {**qm, **rot_model}, balls_w, state)


def chain_links(machine: Machine, estimated: Mapping[str, float]) -> dict[str, float]:
    """Links of the predicted chain: the controller-held ones (``Machine.held_links``) plus the
    estimated ones, summed per ISO name — identification runs relative to the controller."""
    links = machine.held_link_values()
    for name, value in estimated.items():
        links[name] = links.get(name, 0.0) + float(value)
    return links


def predict(
    machine: Machine,
    artefact: Artefact,
    layout: Layout,
    p: np.ndarray,
    centres: Centres,
    *,
    jacobian: bool = False,
    motion_errors: Mapping[str, MotionErrorFn] | None = None,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Predicted centres (K, 3) in controller mm for parameters ``p``; with ``jacobian`` also
    d(predicted)/dp as (K, 3, P). The chain carries the controller-held links of ``machine``
    plus the estimated ones (``chain_links``)."""
    est_links, dballs, dtip, scale = layout.unpack(np.asarray(p, float))
    links = chain_links(machine, est_links)
    state = ChainState(links=links, tip_offset_mm=dtip, linear_scale=scale,
                       motion_errors=motion_errors or {})
    balls_w = artefact.nominal_mm[centres.ball] + dballs[centres.ball]
    rot_model = to_model(machine, rotary_columns(machine, centres.b_deg, centres.c_deg))
    q = centres.xyz_mm.copy()  # the measurement is an excellent first guess
    jq = None
    g0 = _g(machine, rot_model, balls_w, q, state)
    for _ in range(20):
        if jq is None or state.motion_errors:
            # Without motion errors g is affine in the linear joints: dg/dq is constant and a
            # unit step gives it exactly, so it is built once (chord = Newton here).
            jq = np.empty((len(centres), 3, 3))
            for k in range(3):
                dq = q.copy()
                dq[:, k] += 1.0
                jq[:, :, k] = _g(machine, rot_model, balls_w, dq, state) - g0
        step = np.linalg.solve(jq, -g0[..., None])[..., 0]
        q += step
        g0 = _g(machine, rot_model, balls_w, q, state)
        if np.max(np.abs(step)) < 1e-11:
            break
    if not jacobian:
        return q, None

    # dg/dp at the solution, then dq/dp = -(dg/dq)^-1 dg/dp.
    k_obs = len(centres)
    dg = np.zeros((k_obs, 3, layout.size))
    qm = {**to_model(machine, {k: q[:, i] for i, k in enumerate("XYZ")}, state.linear_scale),
          **rot_model}
    if layout.links:
        dg[:, :, : len(layout.links)] = _link_columns(machine, qm, state, balls_w, layout.links)
    # Setup columns are exact: g = F_T_T·tip − F_T_W·ball is linear in both offsets, so a ball
    # offset enters as −R_W and a tip offset as +R_T (rotation parts at the solution).
    f_w, f_t = frames(machine, qm, state)
    rows = np.arange(k_obs)
    for a in range(3):
        dg[rows, :, layout.ball_slice.start + 3 * centres.ball + a] = -f_w[:, :3, a]
        dg[:, :, layout.tip_slice.start + a] = f_t[:, :3, a]
    if layout.scale:
        h = 1e-6
        st_p = ChainState(links, dtip, scale + h, state.motion_errors)
        st_m = ChainState(links, dtip, scale - h, state.motion_errors)
        dg[:, :, -1] = (_g(machine, rot_model, balls_w, q, st_p)
                        - _g(machine, rot_model, balls_w, q, st_m)) / (2 * h)
    dq = -np.linalg.solve(jq, dg)
    return q, dq


_GEN = np.zeros((3, 4, 4))  # generators of the rotations about x, y, z (4×4 skew parts)
_GEN[0, 2, 1], _GEN[0, 1, 2] = 1.0, -1.0
_GEN[1, 0, 2], _GEN[1, 2, 0] = 1.0, -1.0
_GEN[2, 1, 0], _GEN[2, 0, 1] = 1.0, -1.0


def _rot1(index: int, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    m = np.eye(4)
    i, j = [(1, 2), (2, 0), (0, 1)][index]
    m[i, i] = m[j, j] = c
    m[i, j], m[j, i] = -s, s
    return m


def _location_derivatives(axis: Axis, links: Mapping[str, float]) -> dict[str, np.ndarray]:
    """Exact d(L)/d(e) of the location HTM L = Trans(t)·Rot_x(a)·Rot_y(b)·Rot_z(c) of ``axis``
    at the current link values, per ISO name (4×4, the same for every centre); on an inclined
    axis conjugated by its frame R0 as ``kinematics._location_htm`` does (before, the
    derivative of EC0B of the nutating B was taken about z, not R0·z: cos 0.73 with the
    finite difference, a wrong Gauss-Newton direction and covariance for that link)."""
    e = np.zeros(6)
    slot = {}
    for name in axis.location_error_names():
        c = name[1]
        slot[name] = "XYZ".index(c) if c in "XYZ" else 3 + "ABC".index(c)
        e[slot[name]] = links.get(name, 0.0)
    t = np.eye(4)
    t[:3, 3] = e[:3]
    r = [_rot1(k, e[3 + k]) for k in range(3)]
    out = {}
    for name, k in slot.items():
        if k < 3:
            d = np.zeros((4, 4))
            d[k, 3] = 1.0  # d(T·R)/dt_k = E_k3 · R = E_k3
        else:
            f = [r[0], r[1], r[2]]
            f[k - 3] = f[k - 3] @ _GEN[k - 3]  # d Rot_k / d angle = Rot_k · K_k
            d = t @ f[0] @ f[1] @ f[2]
        out[name] = d
    r0 = axis_frame(axis)
    if r0 is not None:  # an inclined axis' errors act in its frame: L = H0·L'·H0ᵀ
        h = np.eye(4)
        h[:3, :3] = r0
        out = {name: h @ d @ h.T for name, d in out.items()}
    return out


def _link_columns(machine: Machine, q_model: Mapping[str, np.ndarray], state: ChainState,
                  balls_w: np.ndarray, names: Sequence[str]) -> np.ndarray:
    """dg/d(link) (K, 3, L) analytically: an error of axis k enters its chain as
    P_k · dL_k · R_k · S_k · point (P: the axes before k, R_k: axis k without its location
    error, S: the axes after k), with a minus sign on the workpiece branch (g = tip − ball)."""
    k_obs = balls_w.shape[0]
    out = np.zeros((k_obs, 3, len(names)))
    col = {n: i for i, n in enumerate(names)}
    tip = np.broadcast_to(np.asarray(machine.tool_tip_mm, float) + state.tip_offset_mm,
                          (k_obs, 3))
    for chain, point, sign in ((machine.workpiece_chain, balls_w, -1.0),
                               (machine.tool_chain, tip, 1.0)):
        wanted = [a for a in chain
                  if any(n in col for n in machine.axes[a].location_error_names())]
        if not wanted:
            continue
        full = [axis_htm(machine.axes[a], np.asarray(q_model[a], float), state.links,
                         state.motion_errors.get(a)) for a in chain]
        # suffix[k] = A_k ⋯ A_n · point (homogeneous), prefix[k] = A_1 ⋯ A_{k-1}
        v = np.concatenate([point, np.ones((k_obs, 1))], axis=1)[..., None]
        suffix = [v] * (len(chain) + 1)
        for k in range(len(chain) - 1, -1, -1):
            suffix[k] = full[k] @ suffix[k + 1]
        prefix = np.broadcast_to(np.eye(4), (k_obs, 4, 4))
        for k, a in enumerate(chain):
            if a in wanted:
                bare = axis_htm(machine.axes[a], np.asarray(q_model[a], float), None,
                                state.motion_errors.get(a))
                tail = bare @ suffix[k + 1]
                for name, d in _location_derivatives(machine.axes[a], state.links).items():
                    if name in col:
                        out[:, :, col[name]] = sign * (prefix @ (d @ tail))[:, :3, 0]
            prefix = prefix @ full[k]
    return out
