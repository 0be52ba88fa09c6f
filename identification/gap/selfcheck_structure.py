"""Self-check conditions outside the library: a cyclic error and a local bump of a linear axis.

``cyclic_error`` injects a cyclic positioning error (a ball screw's pitch error) of 2-8 µm
amplitude and 20-80 mm period, random phase, along the case's axis (X, Y, Z in turn);
``local_bump`` a raised-cosine bump of 4-10 µm (either sign) over 30-80 mm, centred anywhere the
balls' centres reach along the axis, in a random direction (positioning or either straightness).
Both with ``+scatter`` run under the self-check's index scatter. Neither is a library effect:
the diagnosis must read ``unexplained`` or a library effect that takes the held-out gap down to
the floor without the centre scatter (trigger noise and rigid index scatter) — never ``none``,
never a chip or a knocked ball — and locate structure along the right axis (``structure``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from identification.effects import Effect, make_effect
from identification.identifiability import nominal_centres
from identification.kinematics import Machine
from identification.model import Artefact

STRUCTURE = ("cyclic_error", "local_bump")
AXES = ("X", "Y", "Z")
CYCLIC_UM, PERIOD_MM = (2.0, 8.0), (20.0, 80.0)
BUMP_UM, WIDTH_MM = (4.0, 10.0), (30.0, 80.0)
NOT_LIBRARY = ("none", "absorbed", "unexplained", "measurement_outlier", "ball_moved",
               "pole_defect")


def inject(scenario: str, axis: str, machine: Machine, artefact: Artefact,
           poses: Sequence[tuple[float, float]], rng: np.random.Generator
           ) -> tuple[Effect, np.ndarray]:
    """A random instance of the scenario on ``axis`` (the ranges above)."""
    if scenario == "cyclic_error":
        amp, ph = rng.uniform(*CYCLIC_UM), rng.uniform(0.0, 2.0 * np.pi)
        eff = make_effect(scenario, axis, machine, period_mm=rng.uniform(*PERIOD_MM))
        return eff, np.array([amp * np.cos(ph), amp * np.sin(ph)])
    q = nominal_centres(machine, artefact, list(poses)).xyz_mm[:, AXES.index(axis)]
    comp = f"E{AXES[int(rng.integers(3))]}{axis}"
    eff = make_effect(scenario, axis, machine, centre_mm=rng.uniform(q.min(), q.max()),
                      width_mm=rng.uniform(*WIDTH_MM), component=comp)
    return eff, np.array([rng.uniform(*BUMP_UM) * rng.choice([-1.0, 1.0])])


def rigid_after_ratio(rep: dict) -> float:
    """Held-out RMS after the verdict's effects over the held-out floor of that model,
    counting only the floor's trigger noise and rigid index scatter."""
    v, parts = rep["verdict"], rep["noise"].get("parts") or {}
    floor = v["holdout_floor_after_um"] * np.sqrt(parts.get("rigid_share", 1.0))
    return float(v["holdout_rms_after_um"] / max(floor, 1e-12))


def caught(rep: dict, limit: float) -> bool:
    """Read ``unexplained``, or a library effect that takes the held-out gap down to
    ``limit`` × the rigid floor — not ``none``, not a fault of one visit or ball."""
    v = rep["verdict"]
    if v["effect"] == "unexplained":
        return True
    return v["effect"] not in NOT_LIBRARY and rigid_after_ratio(rep) <= limit


def located(rep: dict, axis: str, limit: float) -> bool:
    """Structure found along ``axis`` on the twin's residuals — or a library effect of that
    axis takes the held-out gap down to ``limit`` × the rigid floor (a bump at the end of the
    travel is a straightness to the plan)."""
    st, v = rep.get("structure") or {}, rep["verdict"]
    if st.get("found") and st.get("axis") == axis:
        return True
    return v["effect"] not in NOT_LIBRARY and v["axis"] == axis \
        and rigid_after_ratio(rep) <= limit
