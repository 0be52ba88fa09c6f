"""Effect families that move the ball or the latched reading, not an axis (drift, sag, creep)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from identification.effect_types import UM, XYZ, Effect, EffectContext, need_axis
from identification.kinematics import (
    LINEAR_LETTERS,
    ROTARY_LETTERS,
    ChainState,
    Machine,
    frames,
    rotary_columns,
    to_model,
)


def default_gravity(machine: Machine) -> np.ndarray:
    """Gravity direction in the foundation frame when the machine file does not give it (its
    ``gravity`` key, passed as the ``gravity_dir`` option). A heuristic: a workpiece-side rotary
    axis turning about Y next to the foundation is the rotary table of a horizontal machine
    (thesis WCBXFZYT, seed 001 wBZfXYCt): Y is vertical, gravity −Y. Otherwise a vertical
    machine: gravity −Z. It is wrong for a vertical machine whose trunnion tilts about Y
    (LinuxCNC xyzbc-trt): such a machine file must say ``gravity: [0, 0, -1]``."""
    rot = [a for a in machine.workpiece_chain if a in ROTARY_LETTERS]
    if rot and machine.axes[rot[0]].index == 1:
        return np.array([0.0, -1.0, 0.0])
    return np.array([0.0, 0.0, -1.0])


def unit_vector(v: Sequence[float] | np.ndarray, what: str) -> np.ndarray:
    """A finite, non-zero 3-vector, normalised; ValueError naming ``what`` otherwise."""
    try:
        a = np.asarray(v, float).reshape(-1)
    except (TypeError, ValueError):
        raise ValueError(f"{what}: expected 3 numbers, got {v!r}") from None
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{what}: expected 3 finite numbers, got {v!r}")
    n = float(np.linalg.norm(a))
    if n < 1e-9:
        raise ValueError(f"{what}: must not be the zero vector")
    return a / n


def default_rod_direction(machine: Machine) -> np.ndarray:
    """Rods stand along +z of the last workpiece frame: the project's table convention (the
    pallet face is a plane z = surface_z_mm of that frame, balls on rods above it; DESIGN.md,
    machine file ``table``)."""
    return np.array([0.0, 0.0, 1.0])


def workpiece_rotation(machine: Machine, b_deg: np.ndarray, c_deg: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation foundation ← last workpiece frame of the nominal chain."""
    n = np.asarray(b_deg).shape[0]
    q = to_model(machine, rotary_columns(machine, b_deg, c_deg))
    q.update({a: np.zeros(n) for a in LINEAR_LETTERS if a in machine.axes})
    f_w, _ = frames(machine, q, ChainState())
    return f_w[:, :3, :3]


def thermal_drift(machine: Machine, axis: str | None, model: str = "linear",
                   tau_h: float | None = None) -> Effect:
    # Seed 002 §3.3.4: thermal drift appears as an offset of the measured position that grows
    # with time from the reference thermal state; here per controller axis, linear (µm/h) or
    # first-order exponential (amplitude µm, time constant h).
    letter = need_axis(machine, "thermal_drift", axis, LINEAR_LETTERS)
    col = XYZ.index(letter)
    if model == "linear":
        names, units = (f"drift_{letter}_rate",), ("um/h",)

        def shape(p: np.ndarray, t_h: np.ndarray) -> np.ndarray:
            return p[0] * t_h
    elif model == "exponential" and tau_h is None:
        names, units = (f"drift_{letter}_amplitude", f"drift_{letter}_tau"), ("um", "h")

        def shape(p: np.ndarray, t_h: np.ndarray) -> np.ndarray:
            return p[0] * (1.0 - np.exp(-t_h / max(p[1], 1e-6)))
    elif model == "exponential":
        names, units = (f"drift_{letter}_amplitude",), ("um",)

        def shape(p: np.ndarray, t_h: np.ndarray) -> np.ndarray:
            return p[0] * (1.0 - np.exp(-t_h / tau_h))
    else:
        raise ValueError(f"thermal_drift: model must be 'linear' or 'exponential', got {model!r}")

    def touch(p: np.ndarray, ctx: EffectContext) -> np.ndarray:
        out = np.zeros((len(ctx), 3))
        out[:, col] = shape(p, np.asarray(ctx.t_s, float) / 3600.0) * UM
        return out

    return Effect("thermal_drift", letter, names, units, _touch=touch,
                  linear=not (model == "exponential" and tau_h is None),
                  note="seed 002 §3.3.4: drift of the reading from the reference thermal state")


def gravity_sag(machine: Machine, axis: str | None, gravity_dir: tuple | None = None,
                 rod_dir: tuple | None = None) -> Effect:
    # Thesis §3.3: the rods bend under the ball's weight (1.49 µm computed for the 152 mm rod).
    # A cantilever with an end load deflects by F L^3 / (3 E I) along the load component
    # perpendicular to the rod: ball shift = s · (L / 100 mm)^3 · g_perp, with g_perp the part of
    # the unit gravity vector (foundation frame, rotated into the last workpiece frame) normal to
    # the rod. Its length is sin(angle rod–gravity): it varies with the tilt on a vertical
    # trunnion machine (−Z gravity, rods vertical at A = 0) and is constant, but turns with C in
    # the workpiece frame, on the horizontal thesis machine (−Y gravity, rods horizontal).
    # ``s`` = sag of a 100 mm rod held perpendicular to gravity, µm.
    if axis is not None:
        raise ValueError("gravity_sag: takes no axis")
    g = unit_vector(gravity_dir, "gravity_dir") if gravity_dir is not None \
        else default_gravity(machine)
    u = np.asarray(rod_dir if rod_dir is not None else default_rod_direction(machine), float)
    u = u / np.linalg.norm(u)

    def ball(p: np.ndarray, ctx: EffectContext) -> np.ndarray:
        r = workpiece_rotation(machine, np.asarray(ctx.b_deg), np.asarray(ctx.c_deg))
        g_w = np.einsum("nji,j->ni", r, g)  # R^T g: gravity in the last workpiece frame
        g_perp = g_w - (g_w @ u)[:, None] * u[None, :]
        lever = (np.asarray(ctx.rod_length_mm, float) / 100.0) ** 3
        return p[0] * UM * lever[:, None] * g_perp

    return Effect("gravity_sag", None, ("sag_100mm",), ("um",), _ball=ball,
                  note="thesis §3.3: rod deflection under the ball weight, ∝ L^3 · sin(tilt)")


def probe_pretravel(machine: Machine, axis: str | None, n_directions: int = 5) -> Effect:
    # Thesis §3.4: the probe latches after a pre-travel along the approach direction, which
    # depends on the direction (lobing). The latched position is past the contact point:
    # offset = p(touch) · direction. A part identical for all directions only changes the fitted
    # radius; the rest moves every centre by the same machine-frame vector and ends in the
    # stylus-tip setup ("interpreted as a stylus tip centre setup error", thesis §3.4); what
    # survives is the sphere-fit residual pattern (5 touches, 4 sphere parameters: 1 dof).
    if axis is not None:
        raise ValueError("probe_pretravel: takes no axis")
    names = tuple(f"pretravel_dir{k}" for k in range(1, n_directions + 1))

    def touch(p: np.ndarray, ctx: EffectContext) -> np.ndarray:
        k = np.asarray(ctx.touch, int)
        if np.any((k < 1) | (k > n_directions)):
            raise ValueError(f"probe_pretravel: touch numbers must be 1..{n_directions}")
        d = np.asarray(ctx.direction, float)
        d = d / np.linalg.norm(d, axis=1, keepdims=True)
        return (p[k - 1] * UM)[:, None] * d

    return Effect("probe_pretravel", None, names, ("um",) * n_directions, _touch=touch,
                  note="thesis §3.4: pre-travel by approach direction (lobing)")


def artefact_instability(machine: Machine, axis: str | None, ball_index: int | None = None,
                          n_balls: int | None = None) -> Effect:
    # Thesis §3.3: the method needs the artefact stable during a session; a ball creeping on its
    # rod moves at a constant velocity (µm/h) in the last workpiece frame. The position at t = 0
    # is a setup error, so only the velocity is a new parameter. ``axis`` names the ball (its id);
    # ``ball_index`` is its index in the artefact. Without a ball, every ball creeps (n_balls).
    if ball_index is None:
        if n_balls is None:
            raise ValueError("artefact_instability: give ball_index (one ball) or n_balls (all)")
        balls = list(range(n_balls))
    else:
        balls = [int(ball_index)]
    names = tuple(f"creep_{axis if len(balls) == 1 and axis else f'ball{b}'}_{a}"
                  for b in balls for a in "xyz")

    def ball_fn(p: np.ndarray, ctx: EffectContext) -> np.ndarray:
        v = p.reshape(len(balls), 3) * UM
        out = np.zeros((len(ctx), 3))
        t_h = np.asarray(ctx.t_s, float) / 3600.0
        for i, b in enumerate(balls):
            m = np.asarray(ctx.ball) == b
            out[m] = t_h[m, None] * v[i][None, :]
        return out

    return Effect("artefact_instability", axis, names, ("um/h",) * len(names), _ball=ball_fn,
                  note="thesis §3.3: artefact stability during a session; creep in time")

