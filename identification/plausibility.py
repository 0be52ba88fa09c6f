"""Is a fit physically plausible for the geometry it was made with? A probing log analysed
against the wrong machine file still "converges": the setup and link errors absorb the wrong
geometry (90° link rotations, 180 mm ball offsets) and the residuals stay at the noise. Such
numbers are not a machine's errors; they say the declared geometry is not the one measured.

The rule (``implausible``) compares each estimated quantity with what the declared geometry
allows, with these thresholds:

* link rotations, ``MAX_LINK_ROTATION_RAD`` = 5 mrad (0.29°, 5 mm per metre): squareness and
  axis-orientation errors of machine tools are tens to hundreds of µrad (the thesis' are below
  40 µrad; ISO 230-1 tolerances of the order of 20-100 µrad/m); a machine 5 mrad out of square
  could not hold a tolerance, a wrong topology gives hundreds of mrad.
* link translations, ``MAX_LINK_TRANSLATION_MM`` = 5 mm: the offset of a rotary axis from the
  pivot declared in the machine file (``point_mm``); real offsets are tens of µm, a pivot
  declared 5 mm off would make every 5-axis program miss its part.
* setup errors, the radius of the smallest ball of the artefact: the probing cycle approaches
  each ball from its nominal position (artefact file ball position, machine file tool tip)
  and touches its equator diagonals; a ball or stylus tip off by more than a ball radius would
  not be touched there, so such an offset cannot come from a real measurement of that artefact
  on that machine (the thesis' are below 0.4 mm; the shipped artefact files say ~0.5 mm).
* residual RMS, above both ``MAX_RESIDUAL_UM`` = 100 µm and ``MAX_RESIDUAL_RATIO`` = 50 times
  the measurement noise (the stated centre uncertainty, or the touches' sphere-fit form
  residual): with the right geometry the residuals are the noise plus unmodelled error motions
  (the thesis' are 0.7 µm; a worn machine's tens of µm); far above both, the model does not
  describe what was measured.

Pure math on an ``Estimate``; the caller (``daemon.analysis.identify``) reports the refusal.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from identification.estimate import Estimate
from identification.kinematics import Machine
from identification.model import Artefact

MAX_LINK_ROTATION_RAD = 5e-3
MAX_LINK_TRANSLATION_MM = 5.0
MAX_RESIDUAL_UM = 100.0
MAX_RESIDUAL_RATIO = 50.0
SHOWN = 3  # findings named in the one-line message; the others are counted


@dataclass(frozen=True)
class Finding:
    """One estimated quantity beyond what the declared geometry allows."""

    what: str  # e.g. "link EC0A", "setup of ball B1", "residual RMS"
    value: str  # the estimate, with its unit
    limit: str  # the threshold it exceeds, with its unit

    def __str__(self) -> str:
        return f"{self.what} {self.value} (plausible: {self.limit})"


def setup_limit_mm(artefact: Artefact) -> float:
    """The largest plausible setup error (ball offset, stylus-tip offset): the smallest ball
    radius (see the module doc)."""
    return min(b.diameter_mm for b in artefact.balls) / 2.0


def implausible(machine: Machine, artefact: Artefact, est: Estimate,
                noise_um: float | None = None) -> list[Finding]:
    """The estimated quantities beyond the module's thresholds, largest excess first ([] when
    the fit is plausible). ``noise_um``: the measurement noise of a centre coordinate (µm)
    when the caller knows one independently of this fit; the stated σ is used when the fit
    was given one."""
    found: list[tuple[float, Finding]] = []
    for i, name in enumerate(est.layout.links):
        v = float(est.p[i])
        if name[1] in "ABC":
            if abs(v) > MAX_LINK_ROTATION_RAD:
                found.append((abs(v) / MAX_LINK_ROTATION_RAD, Finding(
                    f"link {name}", f"{v * 1e3:.4g} mrad ({math.degrees(v):.3g}°)",
                    f"±{MAX_LINK_ROTATION_RAD * 1e3:g} mrad")))
        elif abs(v) > MAX_LINK_TRANSLATION_MM:
            found.append((abs(v) / MAX_LINK_TRANSLATION_MM, Finding(
                f"link {name}", f"{v:.4g} mm", f"±{MAX_LINK_TRANSLATION_MM:g} mm")))
    limit = setup_limit_mm(artefact)
    balls, _ = est.balls_um
    probe, _ = est.probe_um
    for what, vec_um in [("setup of the stylus tip", probe),
                         *((f"setup of ball {b}", balls[k]) for k, b in enumerate(est.ball_ids))]:
        norm = float(np.linalg.norm(vec_um)) * 1e-3
        if norm > limit:
            found.append((norm / limit, Finding(
                what, f"{norm:.4g} mm", f"≤ {limit:g} mm, the ball radius")))
    noise = float(np.sqrt(np.mean(np.square(est.sigma_um)))) if est.sigma_given else noise_um
    rms_limit = max(MAX_RESIDUAL_UM, MAX_RESIDUAL_RATIO * noise if noise else 0.0)
    if est.residual_rms_um > rms_limit:
        found.append((est.residual_rms_um / rms_limit, Finding(
            "residual RMS", f"{est.residual_rms_um:.4g} µm",
            f"≤ {rms_limit:g} µm" + (f", {MAX_RESIDUAL_RATIO:g} × the noise {noise:.3g} µm"
                                     if noise and rms_limit > MAX_RESIDUAL_UM else ""))))
    found.sort(key=lambda x: -x[0])
    return [f for _, f in found]


def describe(machine: Machine, artefact: Artefact, findings: list[Finding]) -> str:
    """One line: what does not fit, and the likely cause."""
    shown = "; ".join(str(f) for f in findings[:SHOWN])
    more = f"; and {len(findings) - SHOWN} more" if len(findings) > SHOWN else ""
    return (f"implausible fit for machine {machine.name} ({machine.topology}) with artefact "
            f"{artefact.name}: {shown}{more} — not errors of this machine: wrong machine file "
            "(the data were measured on another machine or topology) or wrong artefact file?")
