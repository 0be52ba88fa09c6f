"""The tolerances of one machine (machines.N.tolerances in daemon.yaml): limits on link errors,
volumetric distortion, drift and measurement health, as the judge applies them."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class Limit:
    """Bounds on |value| (``warn``/``fail``) and on |value − last good| (``drift_*``)."""

    warn: float | None = None
    fail: float | None = None
    drift_warn: float | None = None
    drift_fail: float | None = None


@dataclass(frozen=True)
class Tolerances:
    links: dict[str, Limit] = field(default_factory=dict)  # ISO name → limit (µm or µrad)
    default_translation_um: Limit | None = None  # for identified links without an own limit
    default_rotation_urad: Limit | None = None
    volumetric_max_um: Limit | None = None  # on max over poses and balls of |distortion|
    # Health (measurement validity; exceeded → ERROR, the run says nothing about the machine):
    residual_rms_um: float | None = None  # estimation residual (probe, balls, fixture, drift)
    sphere_radius_spread_um: float | None = 5.0  # |fitted radius − run median| per ball-pose
    sphere_form_um: float | None = None  # sphere-fit form residual RMS per ball-pose
    coverage_k: float = 2.0  # uncertainty guard band for the WARN-on-doubt rule
    run_drift_um: float | None = None  # ball centre shift between two visits of one pose
    # Machine state (exceeded → WARN, the geometry still stated): the TCP drift over the run
    # fitted with the links (identification.drift), per controller axis, µm
    thermal_drift_um: float | None = None
    # per temperature channel (min_c, max_c, change_c), None where not limited: outside → WARN
    temperatures: dict[str, tuple[float | None, float | None, float | None]] = field(
        default_factory=dict)
    # what the limits are derived from (tolerances.basis) and each limit's stated source by
    # its key (``links.EX0C``, ``volumetric_max_um`` …), the manual's "Set the limits"
    basis: str = ""
    sources: dict[str, str] = field(default_factory=dict)
