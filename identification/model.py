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
    ChainState,
    Machine,
    MotionErrorFn,
    rotary_columns,
    tip_minus_ball,
    to_model,
)

_FD_STEP = 1e-6  # central-difference step for link columns (rad or mm)


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

    def __len__(self) -> int:
        return int(self.pose.shape[0])

    def subset(self, mask: np.ndarray) -> Centres:
        t = self.t_s[mask] if self.t_s.size else self.t_s
        return Centres(self.pose[mask], self.ball[mask], self.b_deg[mask], self.c_deg[mask],
                       self.xyz_mm[mask], t)


def _g(machine: Machine, rot_model: Mapping, balls_w: np.ndarray, q_ctrl: np.ndarray,
       state: ChainState) -> np.ndarray:
    qm = to_model(machine, {k: q_ctrl[:, i] for i, k in enumerate("XYZ")}, state.linear_scale)
    return tip_minus_ball(machine, {**qm, **rot_model}, balls_w, state)


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
    d(predicted)/dp as (K, 3, P)."""
    links, dballs, dtip, scale = layout.unpack(np.asarray(p, float))
    state = ChainState(links=links, tip_offset_mm=dtip, linear_scale=scale,
                       motion_errors=motion_errors or {})
    balls_w = artefact.nominal_mm[centres.ball] + dballs[centres.ball]
    rot_model = to_model(machine, rotary_columns(machine, centres.b_deg, centres.c_deg))
    q = centres.xyz_mm.copy()  # the measurement is an excellent first guess
    for _ in range(20):
        g0 = _g(machine, rot_model, balls_w, q, state)
        jq = np.empty((len(centres), 3, 3))
        for k in range(3):
            dq = q.copy()
            dq[:, k] += 1.0  # g is affine in the linear joints: a unit step is exact
            jq[:, :, k] = _g(machine, rot_model, balls_w, dq, state) - g0
        step = np.linalg.solve(jq, -g0[..., None])[..., 0]
        q += step
        if np.max(np.abs(step)) < 1e-11:
            break
    if not jacobian:
        return q, None

    # dg/dp at the solution, then dq/dp = -(dg/dq)^-1 dg/dp.
    k_obs = len(centres)
    dg = np.zeros((k_obs, 3, layout.size))
    for j, name in enumerate(layout.links):
        for sgn in (1.0, -1.0):
            st = ChainState({**links, name: links[name] + sgn * _FD_STEP}, dtip, scale,
                            state.motion_errors)
            dg[:, :, j] += sgn * _g(machine, rot_model, balls_w, q, st)
        dg[:, :, j] /= 2 * _FD_STEP
    # Setup columns are exact: a ball offset moves the ball with F_T_W, the tip offset with F_T_T.
    for a in range(3):
        e = np.zeros(3)
        e[a] = 1.0
        d_ball = (_g(machine, rot_model, balls_w + e, q, state)
                  - _g(machine, rot_model, balls_w, q, state))
        cols = layout.ball_slice.start + 3 * centres.ball + a
        dg[np.arange(k_obs), :, cols] = d_ball
        st = ChainState(links, dtip + e, scale, state.motion_errors)
        dg[:, :, layout.tip_slice.start + a] = _g(machine, rot_model, balls_w, q, st) - \
            _g(machine, rot_model, balls_w, q, state)
    if layout.scale:
        h = 1e-6
        st_p = ChainState(links, dtip, scale + h, state.motion_errors)
        st_m = ChainState(links, dtip, scale - h, state.motion_errors)
        dg[:, :, -1] = (_g(machine, rot_model, balls_w, q, st_p)
                        - _g(machine, rot_model, balls_w, q, st_m)) / (2 * h)
    dq = -np.linalg.solve(jq, dg)
    return q, dq
