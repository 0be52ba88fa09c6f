"""Per-visit errors of the simulated machine: rotary index scatter and knocked balls.

``indexing.repeatability_urad`` (errors file): each indexation of the rotary axes stops at the
command + δ, δ ~ N(0, σ) per axis, drawn from the truth's seed and the indexation's number so
that every touch of one visit sees the same δ and a run is reproducible. ``ball_steps``: from
its time on, a ball sits displaced by its vector (last workpiece frame).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from contracts.yaml_files import ConfigError

_STREAM = 21  # keeps the index draws apart from every other use of the truth's seed


def check(errors: Any, rotary_axes: list[str], ball_ids: list[str], where: str) -> None:
    """``ConfigError`` naming file and key for an axis or a ball the machine does not have."""
    for axis in errors.indexing.repeatability_urad:
        if axis not in rotary_axes:
            raise ConfigError(f"{where}: indexing.repeatability_urad.{axis}: not a rotary axis "
                              f"of this machine (expected some of {rotary_axes})")
    for i, step in enumerate(errors.ball_steps):
        if step.ball not in ball_ids:
            raise ConfigError(f"{where}: ball_steps[{i}].ball: unknown ball {step.ball!r} "
                              f"(artefact {ball_ids})")


def index_error_deg(errors: Any, rotary_axes: list[str], seed: int, indexation: int
                    ) -> np.ndarray:
    """(2,) where the two rotary axes really stop, minus the command (deg), at indexation
    number ``indexation``; zeros without ``indexing``."""
    sig = errors.indexing.repeatability_urad
    out = np.zeros(2)
    if not sig:
        return out
    rng = np.random.default_rng([int(seed), _STREAM, int(indexation)])
    draw = rng.normal(0.0, 1.0, 2)
    for k, axis in enumerate(rotary_axes[:2]):
        out[k] = np.rad2deg(draw[k] * sig.get(axis, 0.0) * 1e-6)
    return out


def step_offsets_mm(errors: Any, ball_ids: list[str], t_s: float) -> np.ndarray:
    """(n, 3) displacement of every ball at machine time ``t_s`` by the steps before it."""
    out = np.zeros((len(ball_ids), 3))
    for step in errors.ball_steps:
        if t_s >= step.t_s:
            out[ball_ids.index(step.ball)] += np.asarray(step.vector_um, float) * 1e-3
    return out
