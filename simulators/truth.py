"""The simulated machine's truth: nominal chain + link, setup and effect errors from an errors file.

The chain is ``identification.kinematics`` (one model shared with the estimator); effects come from
``identification.effects`` (shared with the gap diagnosis) and act through their three
hooks: motion errors in the chain, ball-centre offsets (sag, creep) and latched-position offsets
(thermal drift, pre-travel by direction); the motion errors of the linear axes given as
functions (``motion_errors``, simulators/motion_truth.py) join the effects' in the chain.
Everything is deterministic given the seed.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from contracts.setup_files import MachineFile, load_artefact, load_machine
from contracts.yaml_files import ConfigError
from identification.effects import EffectContext, combine_motion_errors
from identification.kinematics import ChainState, Machine, frames, to_model
from identification.model import Artefact
from simulators import visit_errors
from simulators.errors_schema import ErrorsFile, errors_from_dict, link_to_model, load_errors
from simulators.motion_truth import MotionFunction, chain_functions, motion_functions
from simulators.thermal import ThermalState


@dataclass
class ActiveEffect:
    """An instantiated effect with its parameter vector (in the units the effect declares)."""

    effect: Any  # identification.effects.Effect
    params: np.ndarray


@dataclass
class TruthModel:
    """Everything the simulated machine really is; built by :meth:`build` or :meth:`from_files`."""

    machine: Machine
    machine_file: MachineFile
    artefact: Artefact
    errors: ErrorsFile
    seed: int
    links: dict[str, float]  # model units (mm, rad)
    ball_setup_mm: np.ndarray  # (n, 3) last workpiece frame
    tip_setup_mm: np.ndarray  # (3,) last tool frame
    stylus_radius_mm: float
    absent: set[int]
    obstacle_centres_mm: np.ndarray  # (m, 3) last workpiece frame
    obstacle_radii_mm: np.ndarray  # (m,)
    effects: list[ActiveEffect] = field(default_factory=list)
    thermal: ThermalState | None = None  # warm-up during the run
    # the linear axes' motion errors by ISO name (errors file ``motion_errors``)
    motion: dict[str, MotionFunction] = field(default_factory=dict)
    state: ChainState = field(init=False)
    _affine: dict = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self) -> None:
        motion = combine_motion_errors(chain_functions(self.machine, self.motion),
                                       *(ae.effect.motion_errors(ae.params)
                                         for ae in self.effects))
        self.state = ChainState(links=dict(self.links),
                                tip_offset_mm=np.asarray(self.tip_setup_mm, float),
                                motion_errors=motion)

    # ------------------------------------------------------------------------ construction

    @classmethod
    def from_files(cls, machine_path: Path | str, artefact_path: Path | str,
                   errors_path: Path | str | None = None, seed: int | None = None) -> TruthModel:
        machine, mf = load_machine(machine_path)
        artefact = load_artefact(artefact_path)
        errors = load_errors(errors_path) if errors_path else errors_from_dict({})
        return cls.build(machine, mf, artefact, errors, seed, str(errors_path or "<no errors>"))

    @classmethod
    def build(cls, machine: Machine, machine_file: MachineFile, artefact: Artefact,
              errors: ErrorsFile, seed: int | None = None, where: str = "<errors>"
              ) -> TruthModel:
        """Check the errors against machine and artefact and convert them to model units."""
        seed = errors.seed if seed is None else seed
        if errors.machine is not None and errors.machine != machine.name:
            raise ConfigError(f"{where}: machine: errors are for {errors.machine!r}, "
                              f"the machine file is {machine.name!r}")
        allowed = set(machine.location_error_names())
        links = {}
        for name, v in errors.links.items():
            if name not in allowed:
                raise ConfigError(f"{where}: links.{name}: not a location error of "
                                  f"{machine.topology} (expected one of {sorted(allowed)})")
            links[name] = link_to_model(name, v)
        ids = artefact.ids
        rng = np.random.default_rng(seed)
        balls = np.zeros((len(ids), 3))
        for bid, v in errors.setup.balls_um.items():
            if bid not in ids:
                raise ConfigError(f"{where}: setup.balls_um.{bid}: unknown ball (artefact {ids})")
            balls[ids.index(bid)] = np.asarray(v) * 1e-3
        balls += rng.normal(0.0, errors.setup.random_balls_std_um * 1e-3, balls.shape)
        tip = np.asarray(errors.setup.probe_um) * 1e-3
        tip = tip + rng.normal(0.0, errors.setup.random_probe_std_um * 1e-3, 3)
        absent = set()
        for bid in errors.absent_balls:
            if bid not in ids:
                raise ConfigError(f"{where}: absent_balls: unknown ball {bid!r} (artefact {ids})")
            absent.add(ids.index(bid))
        visit_errors.check(errors, machine.rotary_axes, ids, where)
        obs = errors.obstacles
        effects = [_make_effect(machine, e, where, i, machine_file.gravity)
                   for i, e in enumerate(errors.effects)]
        return cls(
            machine=machine, machine_file=machine_file, artefact=artefact, errors=errors,
            seed=seed, links=links, ball_setup_mm=balls, tip_setup_mm=tip,
            stylus_radius_mm=errors.probe.stylus_diameter_mm / 2.0, absent=absent,
            obstacle_centres_mm=np.array([o.centre_mm for o in obs], float).reshape(-1, 3),
            obstacle_radii_mm=np.array([o.radius_mm for o in obs], float),
            effects=effects,
            thermal=ThermalState.from_file(errors.thermal) if errors.thermal else None,
            motion=motion_functions(machine, errors.motion_errors, where),
        )

    # ------------------------------------------------------------------------- evaluation

    @property
    def rotary_letters(self) -> list[str]:
        return self.machine.rotary_axes

    @property
    def ball_radii_mm(self) -> np.ndarray:
        return np.array([b.diameter_mm / 2.0 for b in self.artefact.balls])

    @property
    def has_motion_errors(self) -> bool:
        return bool(self.state.motion_errors)

    def chain(self, q_ctrl: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For controller joints (S, 5: X Y Z, first rotary, second rotary; mm, deg) return the
        true stylus-tip centre in the foundation frame (S, 3) and the workpiece frame rotation
        (S, 3, 3) and origin (S, 3): a ball at w (last workpiece frame) sits at ``R @ w + t``."""
        q = np.atleast_2d(np.asarray(q_ctrl, float))
        r1, r2 = self.rotary_letters
        qm = to_model(self.machine, {"X": q[:, 0], "Y": q[:, 1], "Z": q[:, 2],
                                     r1: q[:, 3], r2: q[:, 4]})
        f_w, f_t = frames(self.machine, qm, self.state)
        tip_local = np.asarray(self.machine.tool_tip_mm, float) + self.state.tip_offset_mm
        tip = (f_t[:, :3, :3] @ tip_local) + f_t[:, :3, 3]
        return tip, f_w[:, :3, :3], f_w[:, :3, 3]

    def affine_map(self, b_deg: float, c_deg: float) -> tuple[np.ndarray, np.ndarray]:
        """(A, t) with tip-in-workpiece-frame ≈ A @ [X Y Z] + t at this indexation: exact
        without motion errors, within the motion errors (µm) otherwise; cached per pose."""
        key = (float(b_deg), float(c_deg))
        hit = self._affine.get(key)
        if hit is None:
            q = np.zeros((4, 5))
            q[1:, :3] = np.eye(3)
            q[:, 3], q[:, 4] = b_deg, c_deg
            tip, rot, org = self.chain(q)
            tip_w = np.einsum("sji,sj->si", rot, tip - org)
            hit = ((tip_w[1:] - tip_w[0]).T, tip_w[0])
            if len(self._affine) > 4096:
                self._affine.clear()
            self._affine[key] = hit
        return hit

    def context(self, **kw: Any) -> Any:
        """An ``identification.effects.EffectContext`` for N rows (missing fields zero)."""
        n = len(np.atleast_1d(kw["t_s"]))
        ball = np.atleast_1d(kw.get("ball", np.zeros(n, int))).astype(int)
        nominal = self.artefact.nominal_mm[ball] + self.ball_setup_mm[ball]  # as EffectContext
        rods = np.array([b.rod_length_mm for b in self.artefact.balls])[ball]
        return EffectContext(
            t_s=np.broadcast_to(np.asarray(kw["t_s"], float), (n,)).copy(),
            b_deg=np.broadcast_to(np.asarray(kw.get("b_deg", 0.0), float), (n,)).copy(),
            c_deg=np.broadcast_to(np.asarray(kw.get("c_deg", 0.0), float), (n,)).copy(),
            ball=ball,
            touch=np.broadcast_to(np.asarray(kw.get("touch", 0), int), (n,)).copy(),
            direction=np.broadcast_to(np.asarray(kw.get("direction", np.zeros(3)), float),
                                      (n, 3)).copy(),
            xyz_mm=np.broadcast_to(np.asarray(kw.get("xyz_mm", np.zeros(3)), float),
                                   (n, 3)).copy(),
            ball_nominal_mm=nominal,
            rod_length_mm=rods,
        )

    def ball_centres_mm(self, t_s: float, b_deg: float, c_deg: float) -> np.ndarray:
        """True ball centres (n, 3) in the last workpiece frame at time t and this indexation."""
        w = self.artefact.nominal_mm + self.ball_setup_mm
        if self.errors.ball_steps:  # knocked balls
            w = w + visit_errors.step_offsets_mm(self.errors, self.artefact.ids, t_s)
        if self.effects:
            n = len(self.artefact.balls)
            ctx = self.context(t_s=np.full(n, t_s), b_deg=b_deg, c_deg=c_deg, ball=np.arange(n))
            for ae in self.effects:
                w = w + np.asarray(ae.effect.ball_offset_mm(ae.params, ctx), float)
        return w

    def touch_offset_mm(self, t_s: float, b_deg: float, c_deg: float, ball: int, touch: int,
                        direction: np.ndarray, xyz_mm: np.ndarray,
                        thermal_t_s: float | None = None) -> np.ndarray:
        """Additive offset (3,) of a latched controller X Y Z (thermal drift, pre-travel …);
        the effects at ``t_s`` (program time, as the estimator's rows), the warm-up's drift at
        ``thermal_t_s`` (time since the machine's start, simulators/thermal.py; default t_s)."""
        out = np.zeros(3) if self.thermal is None else self.thermal.drift_mm(
            t_s if thermal_t_s is None else thermal_t_s)
        if not self.effects:
            return out
        ctx = self.context(t_s=np.array([t_s]), b_deg=b_deg, c_deg=c_deg, ball=[ball],
                           touch=touch, direction=direction, xyz_mm=xyz_mm)
        for ae in self.effects:
            out += np.asarray(ae.effect.touch_offset_mm(ae.params, ctx), float).reshape(3)
        return out

    def centre_ctrl(self, ball: int, b_deg: float, c_deg: float, t_s: float = 0.0,
                    nominal: bool = False) -> np.ndarray:
        """Controller X Y Z putting the (true, or nominal) tip on a ball centre."""
        from identification.kinematics import solve_centre

        r1, r2 = self.rotary_letters
        rot = {r1: np.array([b_deg]), r2: np.array([c_deg])}
        if nominal:
            w = self.artefact.nominal_mm[ball][None]
            return solve_centre(self.machine, rot, w, ChainState())[0]
        w = self.ball_centres_mm(t_s, b_deg, c_deg)[ball][None]
        return solve_centre(self.machine, rot, w, self.state)[0]


def _make_effect(machine: Machine, e: Any, where: str, i: int,
                 gravity: list[float] | None = None) -> ActiveEffect:
    key = f"{where}: effects[{i}] ({e.family}{'/' + e.axis if e.axis else ''})"
    options = dict(e.options)
    if e.family == "gravity_sag" and gravity is not None:
        # The machine file's gravity, unless the errors file overrides it for this effect.
        options.setdefault("gravity_dir", tuple(gravity))
    try:
        from identification.effects import make_effect
    except ImportError as exc:
        raise ConfigError(f"{key}: effect models are not available "
                          f"(identification.effects: {exc})") from None
    try:
        eff = make_effect(e.family, e.axis, machine, **options)
    except (ValueError, KeyError, TypeError) as exc:
        raise ConfigError(f"{key}: {exc}") from None
    names = tuple(eff.param_names)
    unknown = sorted(set(e.params) - set(names))
    if unknown:
        raise ConfigError(f"{key}: params: unknown {unknown} (expected {list(names)} in "
                          f"{list(eff.units)})")
    missing = [n for n in names if n not in e.params]
    if missing:
        raise ConfigError(f"{key}: params: missing {missing} (units {list(eff.units)})")
    return ActiveEffect(eff, np.array([e.params[n] for n in names], float))
