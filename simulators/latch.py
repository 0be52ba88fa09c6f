"""What the probe latches on one probing move: the touch and ball it is, where it switches, errors.

The contact itself is geometry (``simulators.probe``); here the switch follows it by the
pre-travel (or a fault moves or removes it), and the latched position gets the effect offsets
of the true machine and the probing noise (thesis §3.4 repeatability).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from contracts.messages import TOUCH_DIRECTIONS
from contracts.touch_frame import EQUATOR_TURNS_DEG, equator_directions
from identification.kinematics import ChainState, frames, to_model
from simulators import visit_errors
from simulators.faults import Fault
from simulators.gcode import Alarm
from simulators.probe import first_contact
from simulators.truth import TruthModel

EARLY_TRIGGER_TARGET = -999  # contact_target of a switch a fault fired before any contact


@dataclass
class TouchRecord:
    """Everything the controller knows about one probing move (for the offline log)."""

    seq: int
    t_s: float
    start: np.ndarray
    end: np.ndarray
    latched: dict[str, float]
    triggered: bool
    feed_mm_min: float
    touch: int  # 1..5 recognised from the move direction, 0 otherwise
    direction: tuple[float, float, float]
    ball: int  # ball index the move aims at (nearest nominal centre), -1 none
    contact_target: int | None  # what the stylus met (ball index, -1-k obstacle), None


@dataclass(frozen=True)
class Latch:
    """One probing move as the probe saw it; ``fraction`` None: it never switched."""

    touch: int  # 1..5 recognised from the move direction, 0 otherwise
    direction: tuple[float, float, float]
    ball: int  # ball index the move aims at (nearest nominal centre)
    length_mm: float
    fraction: float | None  # of the move where it stopped (latched), None: ran to its end
    target: int | None  # what the stylus met (ball index, -1-k obstacle), None
    stop: np.ndarray  # where the axes stopped, controller X Y Z
    xyz: np.ndarray  # the latched controller X Y Z (the end point on a miss)

    @property
    def triggered(self) -> bool:
        return self.fraction is not None


@dataclass
class _Visit:
    key: tuple = ()
    noise_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))
    touches: set[int] = field(default_factory=set)


class ProbeLatch:
    """The touch probe of the virtual CNC on a ``TruthModel``, with its own noise generator."""

    def __init__(self, truth: TruthModel, rng_seed: int) -> None:
        self.truth = truth
        self._nominal_cache: dict[tuple[float, float], np.ndarray] = {}
        self._spindle_cache: dict[tuple[float, float], np.ndarray | None] = {}
        self.reseed(rng_seed)

    def reseed(self, seed: int) -> None:
        """Restart the noise sequence and forget the current ball visit."""
        self._rng = np.random.default_rng(seed)
        self._visit = _Visit()

    def latch(self, p0: np.ndarray, p1: np.ndarray, b: float, c: float, t: float,
              faults: list[Fault], rotary_moves: int, feed_mm_min: float = 0.0,
              locate: bool = False, thermal_t_s: float | None = None) -> Latch:
        """The probing move p0 → p1 (controller X Y Z, rotary axes at b, c) at machine time t
        (from the program's start; the warm-up's drift at ``thermal_t_s``, the machine's clock,
        default t) and ``feed_mm_min``, with the probing faults due on it; ``rotary_moves`` counts
        indexations so far. The switch is sampled every ``probe.sample_period_ms``: the latch
        lies past the contact by v·T·U(0, 1) (config/linuxcnc/README.md, servo-period
        overshoot), so its scatter grows with the feed. ``locate``: the fast approach of a
        two-speed touch — where the axes stopped, no noise and no visit of its own (the
        re-touch is the touch)."""
        truth = self.truth
        length = float(np.linalg.norm(p1 - p0))
        u = (p1 - p0) / length
        touch, direction = self._touch_number(u, b, c)
        ball = self._aimed_ball(p1, b, c)
        kinds = {f.kind for f in faults}
        # Where the rotary axes really stopped at this indexation (index scatter).
        db, dc = visit_errors.index_error_deg(truth.errors, truth.rotary_letters, truth.seed,
                                              rotary_moves)
        contact = None if "no_trigger" in kinds else first_contact(truth, p0, p1, b + db,
                                                                   c + dc, t)
        s_latch = None
        target_id = None
        if "early_trigger" in kinds:
            frac = next(f.fraction for f in faults if f.kind == "early_trigger")
            if contact is None or frac < contact.s:
                s_latch, target_id = frac, EARLY_TRIGGER_TARGET
        if s_latch is None and contact is not None:
            s_latch = contact.s + (truth.errors.probe.pretravel_um * 1e-3
                                   + self._sampled_mm(feed_mm_min)) / length
            target_id = contact.target
            if s_latch > 1.0:
                s_latch = None  # the move ended before the probe switched
        if s_latch is None:
            return Latch(touch, direction, ball, length, None, target_id, p1, p1.copy())
        stop = p0 + s_latch * (p1 - p0)
        if locate:
            return Latch(touch, direction, ball, length, s_latch, target_id, stop, stop.copy())
        xyz = stop + self._errors(u, t, b, c, touch, direction, stop, rotary_moves,
                                  target_id if target_id is not None and target_id >= 0
                                  else ball, t if thermal_t_s is None else thermal_t_s)
        return Latch(touch, direction, ball, length, s_latch, target_id, stop, xyz)

    def _sampled_mm(self, feed_mm_min: float) -> float:
        """How far past the contact the sampled switch is seen (0 with a continuous latch)."""
        period_s = self.truth.errors.probe.sample_period_ms * 1e-3
        if period_s <= 0 or feed_mm_min <= 0:
            return 0.0  # no draw: the noise sequence of a continuous latch is unchanged
        return feed_mm_min / 60.0 * period_s * float(self._rng.uniform())

    def _touch_number(self, u: np.ndarray, b: float, c: float
                      ) -> tuple[int, tuple[float, float, float]]:
        """Touch 1..5 from the move direction (controller X Y Z = tool relative to workpiece);
        the pole comes against the spindle axis. Where a head tilts the spindle the
        touches are in the tool frame at that pose (``contracts.touch_frame``, any of the
        equator turns a tilted-probe program may use), so a visit's touches keep their numbers
        and share the visit's centre scatter as on a table-table machine."""
        dirs = dict(TOUCH_DIRECTIONS)
        dirs[5] = tuple(-np.asarray(self.truth.machine.spindle_axis, float))
        best, k = max((float(np.dot(u, d)), k) for k, d in dirs.items())
        if best > 0.999:
            return k, tuple(float(x) for x in dirs[k])
        s = self._tilted_spindle(b, c)
        for turn in EQUATOR_TURNS_DEG if s is not None else ():
            td = equator_directions(s, turn)
            best, k = max((float(np.dot(u, d)), k) for k, d in td.items())
            if best > 0.999:
                return k, tuple(float(x) for x in td[k])
        return 0, tuple(float(x) for x in u)

    def _tilted_spindle(self, b: float, c: float) -> np.ndarray | None:
        """The nominal spindle direction at this indexation when a head tilts it, else None."""
        key = (round(b, 6), round(c, 6))
        if key not in self._spindle_cache:
            m = self.truth.machine
            r1, r2 = self.truth.rotary_letters
            zero = np.zeros(1)
            _, f_t = frames(m, to_model(m, {"X": zero, "Y": zero, "Z": zero,
                                           r1: np.array([b]), r2: np.array([c])}), ChainState())
            home = np.asarray(m.spindle_axis, float)
            s = f_t[0, :3, :3] @ home
            self._spindle_cache[key] = s if np.linalg.norm(np.cross(s, home)) > 1e-9 else None
        return self._spindle_cache[key]

    def _aimed_ball(self, end: np.ndarray, b: float, c: float) -> int:
        key = (round(b, 6), round(c, 6))
        if key not in self._nominal_cache:
            n = len(self.truth.artefact.balls)
            self._nominal_cache[key] = np.array(
                [self.truth.centre_ctrl(i, b, c, nominal=True) for i in range(n)])
        d = np.linalg.norm(self._nominal_cache[key] - end, axis=1)
        return int(np.argmin(d))

    def _errors(self, u: np.ndarray, t: float, b: float, c: float, touch: int,
                direction: tuple, stop: np.ndarray, rotary_moves: int, ball: int,
                thermal_t_s: float) -> np.ndarray:
        """Effect offsets + probing noise: per touch along the approach, per ball visit common
        to its touches (thesis §3.4 repeatability)."""
        probe = self.truth.errors.probe
        # A visit ends when the ball or the indexation changes, or a touch number comes back
        # (the next repeat of the same ball). The generator orders the four equator touches by
        # path length, so touch numbers need not increase within one visit.
        key = (ball, round(b, 6), round(c, 6), rotary_moves)
        if key != self._visit.key or touch in self._visit.touches:
            self._visit = _Visit(key, self._rng.normal(0.0, 1.0, 3)
                                 * np.asarray(probe.centre_noise_um) * 1e-3)
        self._visit.touches.add(touch)
        noise = self._visit.noise_mm + u * self._rng.normal(0.0, probe.touch_noise_um * 1e-3)
        try:
            eff = self.truth.touch_offset_mm(t, b, c, ball, touch, np.asarray(direction), stop,
                                             thermal_t_s)
        except ValueError as e:
            raise Alarm(f"simulator effect model: {e}") from None
        return eff + noise
