"""Exact synthetic placements for the map tests: a machine with known links and motion errors,
ball centres solved on its chain and five touches where its stylus really meets each ball
(no simulator program: seconds, not minutes)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np

from contracts.messages import TOUCH_DIRECTIONS
from contracts.probing_log import LogRow
from identification.kinematics import (
    ChainState,
    Machine,
    rotary_columns,
    solve_centre,
    tip_minus_ball,
    to_model,
)
from identification.linmap.problem import Placement
from identification.model import Artefact, Ball, CalibratedDistance, Centres
from simulators.errors_schema import MotionErrorsFile
from simulators.motion_truth import MotionFunction, chain_functions, motion_functions

STYLUS_R = 3.0


@dataclass
class MapTruth:
    machine: Machine
    links: dict[str, float]  # mm / rad
    functions: dict[str, MotionFunction]
    tip_mm: np.ndarray

    @property
    def state(self) -> ChainState:
        return ChainState(links=self.links, tip_offset_mm=self.tip_mm,
                          motion_errors=chain_functions(self.machine, self.functions))

    def field_mm(self, xyz: np.ndarray) -> np.ndarray:
        """True tip minus nominal in the workpiece frame at controller X Y Z, rotary 0."""
        from identification.kinematics import frames

        m = self.machine
        q = {a: xyz[:, i] for i, a in enumerate("XYZ")}
        q.update({r: np.zeros(len(xyz)) for r in m.rotary_axes})
        qm = to_model(m, q)

        def tip_w(state: ChainState) -> np.ndarray:
            f_w, f_t = frames(m, qm, state)
            t = f_t[:, :3, :3] @ np.asarray(m.tool_tip_mm, float) + f_t[:, :3, 3]
            return np.einsum("sji,sj->si", f_w[:, :3, :3], t - f_w[:, :3, 3])

        st = ChainState(links=self.links, motion_errors=self.state.motion_errors)
        return tip_w(st) - tip_w(ChainState())


def map_truth(machine: Machine, seed: int, order: int = 3,
              links: Mapping[str, float] | None = None,
              ranges_mm: Mapping[str, Sequence[float]] | None = None) -> MapTruth:
    spec = {"random_smooth": {"seed": seed, "translation_um": [5, 20],
                              "rotation_urad": [10, 30], "order": order,
                              "range_mm": dict(ranges_mm or {})}}
    fns = motion_functions(machine, MotionErrorsFile.model_validate(spec), "test")
    rng = np.random.default_rng(seed)
    return MapTruth(machine, dict(links or {}), fns, rng.normal(0.0, 0.05, 3))


def moved(artefact: Artefact, shift_mm: Sequence[float], scale: float = 1.0,
          name: str = "moved") -> Artefact:
    """The artefact's balls placed elsewhere on the table (a second placement)."""
    balls = tuple(Ball(b.id, tuple(float(scale * p + s) for p, s in
                                   zip(b.position_mm, shift_mm, strict=True)))
                  for b in artefact.balls)
    return replace(artefact, name=name, balls=balls)


def with_true_distance(artefact: Artefact, balls_mm: np.ndarray, a: int = 0, b: int = 2
                       ) -> Artefact:
    w = artefact.nominal_mm + balls_mm
    d = float(np.linalg.norm(w[a] - w[b]))
    ids = artefact.ids
    return replace(artefact, distances=(CalibratedDistance(ids[a], ids[b], d, 0.5),))


def _touch_points(truth: MapTruth, rot: dict, balls_w: np.ndarray, q0: np.ndarray,
                  rho: np.ndarray) -> np.ndarray:
    """(K, 5, 3) controller points where the true stylus meets each ball along the nominal
    touch directions (Newton along the approach line through the true centre)."""
    m, st = truth.machine, truth.state
    dirs = np.array([TOUCH_DIRECTIONS[t] for t in range(1, 6)])
    k = len(q0)
    start = np.repeat(q0, 5, axis=0)
    d = np.tile(dirs, (k, 1))
    r5 = {a: np.repeat(v, 5) for a, v in rot.items()}
    b5 = np.repeat(balls_w, 5, axis=0)
    rho5 = np.repeat(rho, 5)
    s = rho5.copy()

    def f(s: np.ndarray) -> np.ndarray:
        q = start - d * s[:, None]
        qm = to_model(m, {a: q[:, i] for i, a in enumerate("XYZ")})
        return np.linalg.norm(tip_minus_ball(m, {**qm, **r5}, b5, st), axis=1) - rho5

    for _ in range(6):
        f0 = f(s)
        s = s - f0 / ((f(s + 1e-3) - f0) / 1e-3)
    return (start - d * s[:, None]).reshape(k, 5, 3)


def placement(truth: MapTruth, name: str, artefact: Artefact,
              poses: Sequence[tuple[float, float]], balls_mm: np.ndarray,
              touch_noise_um: float = 0.0, seed: int = 0, touches: bool = True,
              ) -> tuple[Placement, list[LogRow], np.ndarray]:
    """(placement with its touches, the probing-log rows, the exact centres (K, 3))."""
    m = truth.machine
    n = len(artefact.balls)
    pb = np.array(poses, float)
    bc = np.repeat(pb, n, axis=0)
    w = np.tile(artefact.nominal_mm + balls_mm, (len(pb), 1))
    rot = rotary_columns(m, bc[:, 0], bc[:, 1])
    q0 = solve_centre(m, rot, w, truth.state)
    rho = np.array([b.diameter_mm / 2 for b in artefact.balls] * len(pb)) + STYLUS_R
    pts = _touch_points(truth, to_model(m, rot), w, q0, rho)
    rng = np.random.default_rng(seed)
    dirs = np.array([TOUCH_DIRECTIONS[t] for t in range(1, 6)])
    pts = pts - dirs[None] * rng.normal(0.0, touch_noise_um * 1e-3, pts.shape[:2])[..., None]
    pose = np.repeat(np.arange(len(pb)), n)
    ball = np.tile(np.arange(n), len(pb))
    rows, seq = [], 0
    for g in range(len(q0)):
        for t in range(5):
            seq += 1
            rows.append(LogRow(name, seq, seq * 4.0, 0, int(pose[g]), float(bc[g, 0]),
                               float(bc[g, 1]), artefact.ids[ball[g]], t + 1,
                               *map(float, dirs[t]), *map(float, pts[g, t]),
                               float(bc[g, 0]), float(bc[g, 1]), 300.0))
    from identification.spherefit import fit_spheres

    fit = fit_spheres(pts, rho)
    c = Centres(pose, ball, bc[:, 0], bc[:, 1], fit.centre_mm, np.arange(len(q0)) * 20.0)
    pl = Placement(name, artefact, c, pts if touches else None, rho if touches else None)
    return pl, rows, q0


def write_artefact(artefact: Artefact, path) -> None:
    """An artefact YAML file of ``artefact`` (positions, rods, calibrated distances)."""
    import yaml

    data = {"name": artefact.name, "ball_diameter_mm": artefact.balls[0].diameter_mm,
            "balls": [{"id": b.id, "position_mm": list(b.position_mm),
                       "rod_length_mm": b.rod_length_mm} for b in artefact.balls],
            "distances": [{"balls": [d.ball_a, d.ball_b], "distance_mm": d.distance_mm,
                           "std_um": d.std_um} for d in artefact.distances]}
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
