"""The twin (nominal machine + setup + link errors) and every candidate effect as design columns.

The twin is fitted on the exact chain (Gauss-Newton on ``model.predict``, METHOD.md §3). The
diagnosis then works in the linearisation at that estimate: base columns d(obs)/d(twin params)
and, per candidate effect, d(obs)/d(effect params) — the effect's motion errors through the exact
chain (finite difference of ``predict`` with unit parameter steps), its ball offsets through the
ball-setup Jacobian, its touch offsets through the sphere-fit operators (``data.Groups``). All
library effects are linear in their parameters and of µm size, so "twin + effect, refit" becomes
a linear least-squares problem whose neglected second-order terms are < 1 nm for µrad-level
errors on a 1 m lever arm; every fold of the cross-validation is then a cheap solve.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from identification.effects import Effect, EffectContext
from identification.gap.data import Groups, TouchData
from identification.identifiability import identifiable_links
from identification.kinematics import Machine, MotionErrorFn
from identification.model import Artefact, Centres, Layout, predict
from identification.touch_frame import axis_maps

_GN_ITER = 12
_STEP_TOL_MM = 1e-10


@dataclass
class Twin:
    """Linearised twin at the estimate ``p``: observations (G, 4) µm = centre x y z, form."""

    machine: Machine
    artefact: Artefact
    layout: Layout
    p: np.ndarray  # model units (mm, rad)
    names: list[str]
    dropped: dict[str, str]  # unobservable links and what absorbs them
    # the base distortion per (groups, base prediction) the effects' columns are taken at: the
    # same for every effect of a diagnosis (kept with its inputs, so an id is never reused)
    _base_dist: list[tuple[Groups, np.ndarray, np.ndarray]] = field(
        default_factory=list, init=False, repr=False, compare=False)

    def axis_map(self, centres: Centres, q_mm: np.ndarray, p: np.ndarray | None = None,
                 motion: dict[str, MotionErrorFn] | None = None) -> np.ndarray:
        """(G, 3, 3) d(tip − ball)/d(controller X Y Z) at ``q_mm``: how the chain maps a
        controller displacement to a relative displacement of stylus and ball
        (``identification.touch_frame.axis_maps``, the map the analysis fits spheres in)."""
        return axis_maps(self.machine, self.layout, self.p if p is None else p, centres, q_mm,
                         motion)

    def base_distortion_um(self, groups: Groups, q_mm: np.ndarray) -> np.ndarray:
        """``distortion_um`` of the twin's axis map at ``q_mm``, computed once per inputs."""
        for g, q, d in self._base_dist:
            if g is groups and q is q_mm:
                return d
        d = distortion_um(groups, self.axis_map(groups.centres, q_mm))
        self._base_dist.append((groups, q_mm, d))
        return d

    def predicted_um(self, centres: Centres, groups: Groups) -> np.ndarray:
        q, _ = predict(self.machine, self.artefact, self.layout, self.p, centres)
        dist = distortion_um(groups, self.axis_map(centres, q))
        return np.concatenate([q * 1e3, np.zeros((len(centres), 1))], axis=1) + dist

    def base_columns(self, centres: Centres, groups: Groups, q_mm: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
        """(G, 4, P) µm per model unit, and the ball-setup Jacobian (G, 3, 3) mm/mm. Link
        errors also distort the probed sphere (a squareness shears it): finite differences."""
        _, jac = predict(self.machine, self.artefact, self.layout, self.p, centres,
                         jacobian=True)
        cols = np.concatenate([jac, np.zeros((len(centres), 1, jac.shape[2]))], axis=1) * 1e3
        h = 1e-5  # rad or mm: the distortion is linear in µrad-level links to ~1e-5
        d0 = distortion_um(groups, self.axis_map(centres, q_mm))
        for j in range(len(self.layout.links)):
            pp = self.p.copy()
            pp[j] += h
            cols[:, :, j] += (distortion_um(groups, self.axis_map(centres, q_mm, pp)) - d0) / h
        s = self.layout.ball_slice.start
        jb = np.stack([jac[np.arange(len(centres)), :, s + 3 * centres.ball + a]
                       for a in range(3)], axis=2)
        return cols, jb


def fit_twin(machine: Machine, artefact: Artefact, centres: Centres,
             weights: np.ndarray | None = None) -> Twin:
    """Setup + identifiable link errors by Gauss-Newton on the exact chain from zero.

    ``weights`` (G, 3, 3): per-centre whitening matrices (inverse Cholesky factors)."""
    ident = identifiable_links(machine, artefact, centres)
    layout = Layout(tuple(ident.links), len(artefact.balls))
    p = np.zeros(layout.size)
    for _ in range(_GN_ITER):
        q, jac = predict(machine, artefact, layout, p, centres, jacobian=True)
        r = centres.xyz_mm - q
        if weights is not None:
            r = np.einsum("gij,gj->gi", weights, r)
            jac = np.einsum("gij,gjp->gip", weights, jac)
        a = jac.reshape(-1, layout.size)
        norms = np.linalg.norm(a, axis=0)
        norms[norms == 0] = 1.0
        step, *_ = np.linalg.lstsq(a / norms, r.reshape(-1), rcond=1e-10)
        step /= norms
        p += step
        # Angles count as their effect at 1 m (thesis B.4 stop criterion on the step norm).
        scale = np.ones_like(p)
        scale[: len(layout.links)] = [1e3 if n[1] in "ABC" else 1.0 for n in layout.links]
        if np.max(np.abs(step * scale)) < _STEP_TOL_MM:
            break
    return Twin(machine, artefact, layout, p, layout.names(artefact.ids), dict(ident.dropped))


def distortion_um(groups: Groups, amap: np.ndarray) -> np.ndarray:
    """(G, 4) µm: how the chain's axis map bends the probed sphere into an ellipsoid in
    controller coordinates. A touch along the measured normal n lies where |A ρ n| = R, i.e.
    ρ = R / |A n|; the radial deviations ρ − R move the fitted centre and the form residual
    (the sphere-fit operators); the radius change is absorbed by the free radius."""
    an = np.einsum("gij,gtj->gti", amap, groups.normal)
    rho = groups.radius_mm[:, None] / np.linalg.norm(an, axis=2)
    return groups.radial_effect(rho - groups.radius_mm[:, None])


def touch_context(data: TouchData, twin: Twin) -> EffectContext:
    """Effect context per touch; ball positions = nominal + the twin's setup estimate."""
    _, balls, _, _ = twin.layout.unpack(twin.p)
    nominal = twin.artefact.nominal_mm + balls
    rods = np.array([b.rod_length_mm for b in twin.artefact.balls])
    return EffectContext(
        t_s=np.asarray(data.t_s, float), b_deg=np.asarray(data.b_deg, float),
        c_deg=np.asarray(data.c_deg, float), ball=np.asarray(data.ball, int),
        touch=np.asarray(data.touch, int), direction=np.asarray(data.direction, float),
        xyz_mm=np.asarray(data.xyz_mm, float), ball_nominal_mm=nominal[data.ball],
        rod_length_mm=rods[data.ball])


def _stacked_motion(maps: list[dict[str, MotionErrorFn]], n: int) -> dict[str, MotionErrorFn]:
    """One motion-error map for m copies of n rows: copy j uses ``maps[j]``. Lets the chain be
    evaluated once for every unit parameter step of an effect instead of once per step."""
    letters = sorted({k for mp in maps for k in mp})

    def make(letter: str) -> MotionErrorFn:
        fns = [mp.get(letter) for mp in maps]

        def fn(q: np.ndarray) -> np.ndarray:
            qq = np.asarray(q, float).reshape(len(maps), n)
            out = np.zeros((len(maps), n, 6))
            for j, f in enumerate(fns):
                if f is not None:
                    out[j] = np.asarray(f(qq[j]), float).reshape(n, 6)
            return out.reshape(-1, 6)

        return fn

    return {k: make(k) for k in letters}


def _tile(c: Centres, m: int) -> Centres:
    return Centres(np.tile(c.pose, m), np.tile(c.ball, m), np.tile(c.b_deg, m),
                   np.tile(c.c_deg, m), np.tile(c.xyz_mm, (m, 1)),
                   np.tile(c.t_s, m) if c.t_s.size else c.t_s)


def effect_columns(effect: Effect, twin: Twin, groups: Groups, ctx: EffectContext,
                   ball_jac: np.ndarray, base_pred_mm: np.ndarray) -> np.ndarray:
    """(G, 4, m): change of the observations (µm) per unit of each effect parameter."""
    m = effect.n_params
    n = len(groups)
    out = np.zeros((n, 4, m))
    c = groups.centres
    units = np.eye(m)
    maps = [effect.motion_errors(units[j]) for j in range(m)]
    if any(maps):
        motion = _stacked_motion(maps, n)
        tiled = _tile(c, m)
        q, _ = predict(twin.machine, twin.artefact, twin.layout, twin.p, tiled,
                       motion_errors=motion)
        amap = twin.axis_map(tiled, q, motion=motion)
        base_dist = twin.base_distortion_um(groups, base_pred_mm)
        for j in range(m):
            rows = slice(j * n, (j + 1) * n)
            out[:, :3, j] += (q[rows] - base_pred_mm) * 1e3
            out[:, :, j] += distortion_um(groups, amap[rows]) - base_dist
    g = np.zeros(len(ctx), int)  # touches of dropped groups: unused
    g[groups.touch_index.reshape(-1)] = np.repeat(np.arange(n), 5)
    for j in range(m):
        touch = effect.touch_offset_mm(units[j], ctx)
        ball = effect.ball_offset_mm(units[j], ctx)
        if np.any(ball):
            # A ball displacement δw moves the latched point like a ball-setup change of δw.
            touch = touch + np.einsum("nij,nj->ni", ball_jac[g], ball)
        if np.any(touch):
            out[:, :, j] += groups.touch_effect(touch)
    return out
