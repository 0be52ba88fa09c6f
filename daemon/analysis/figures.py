"""A run's reported quantities defined once: value, unit, label and a one-sentence definition."""

# The report, its PDF and JSON, the HMI, the fleet page, the CLI and the
# compensation panel all take a run's figures from here, so that one run tells one story.
# Two distortions exist and are named apart: the distortion measured at the probed poses
# (what the verdict judges) and the distortion the identified link errors alone cause once the
# part the setup errors absorb is removed (what a compensation can act on; smaller by
# construction, it holds neither the setup-absorbed part nor the measurement noise).

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

from daemon.analysis.result import Analysis

VOLUMETRIC = "volumetric_max_um"
AFTER_LINKS = "volumetric_after_links_max_um"
LINK_CAUSED_RMS, LINK_CAUSED_MAX = "link_caused_rms_um", "link_caused_max_um"
PREDICTED_RMS, PREDICTED_MAX = "predicted_after_rms_um", "predicted_after_max_um"

LABELS = {
    VOLUMETRIC: "max volumetric distortion (probed poses)",
    AFTER_LINKS: "max residual after the link errors (probed poses)",
    LINK_CAUSED_RMS: "link-caused distortion RMS",
    LINK_CAUSED_MAX: "link-caused distortion max",
    PREDICTED_RMS: "predicted after compensation RMS",
    PREDICTED_MAX: "predicted after compensation max",
}
DEFINITIONS = {
    VOLUMETRIC: "the largest length of measured minus predicted ball centre over every probed "
                "ball and pose (estimation and held-out poses), predicted by the nominal "
                "machine with this run's setup errors (thesis Eq. 3.22); the verdict judges it",
    AFTER_LINKS: "the same vectors once this run's identified link errors are added to the "
                 "prediction: what the link model leaves unexplained (noise, unmodelled errors)",
    LINK_CAUSED_MAX: "the distortion this run's identified link errors alone cause at the "
                     "estimation poses, every ball, without the part the setup errors absorb "
                     "(what a controller compensation can act on; smaller than the probed-pose "
                     "distortion, which also holds that part and the probing noise)",
    PREDICTED_MAX: "the link-caused distortion predicted to remain once the proposed controller "
                   "changes are written (a prediction; the verification run measures it)",
}
DEFINITIONS[LINK_CAUSED_RMS] = DEFINITIONS[LINK_CAUSED_MAX]
DEFINITIONS[PREDICTED_RMS] = DEFINITIONS[PREDICTED_MAX]
LINK_DEFINITION = ("link errors: this run's own estimate (setup and link errors together, "
                   "every visit of the estimation poses, with the fitted TCP drift when one "
                   "was selected), ISO 230-1 names, u the standard uncertainty (k = 1)")


@dataclass(frozen=True)
class Figure:
    """One reported quantity of one run."""

    key: str
    value: float | None
    unit: str = "µm"

    @property
    def label(self) -> str:
        return LABELS[self.key]

    @property
    def definition(self) -> str:
        return DEFINITIONS[self.key]

    def text(self, digits: int = 1) -> str:
        """``label value unit`` as every surface prints it ("—" when absent)."""
        v = "—" if self.value is None else f"{self.value:.{digits}f} {self.unit}"
        return f"{self.label} {v}"

    def as_dict(self) -> dict[str, Any]:
        return {"key": self.key, "label": self.label, "value": self.value, "unit": self.unit,
                "definition": self.definition}


def volumetric_max_um(analysis: Analysis, after_links: bool = False) -> float | None:
    """Largest distortion vector norm over every probed ball and pose (µm), None if absent."""
    vecs = [v.error_after_links_um if after_links else v.error_um for v in analysis.volumetric]
    norms = [math.hypot(*v) for v in vecs if v is not None]  # type: ignore[arg-type]
    return max(norms) if norms else None


def run_figures(analysis: Analysis) -> tuple[Figure, Figure]:
    """The distortions measured at the probed poses (rounded to 0.1 µm, as shown)."""
    return (Figure(VOLUMETRIC, _r(volumetric_max_um(analysis))),
            Figure(AFTER_LINKS, _r(volumetric_max_um(analysis, after_links=True))))


def plan_figures(before_um: Sequence[float], after_um: Sequence[float]) -> tuple[Figure, ...]:
    """A compensation plan's (rms, max) link-caused distortion before and predicted after."""
    return (Figure(LINK_CAUSED_RMS, _r(before_um[0])), Figure(LINK_CAUSED_MAX, _r(before_um[1])),
            Figure(PREDICTED_RMS, _r(after_um[0])), Figure(PREDICTED_MAX, _r(after_um[1])))


def figures_json(figs: Iterable[Figure]) -> list[dict[str, Any]]:
    return [f.as_dict() for f in figs]


def _r(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else round(float(x), 1)


# ------------------------------------------------------------------------ link error names

_AXIS_OF = {"A": "X", "B": "Y", "C": "Z"}


def plain_name(iso: str) -> str:
    """An ISO 230-1 location error in words, e.g. EX0C → "X offset of the C axis line"."""
    if len(iso) != 4 or iso[0] != "E" or iso[2] != "0":
        return iso
    kind, axis = iso[1], iso[3]
    if kind in "XYZ":
        return f"{kind} offset of the {axis} axis line"
    about = _AXIS_OF.get(kind, kind)
    if axis in "ABC":
        return f"tilt of the {axis} axis line about {about}"
    return f"squareness of the {axis} axis about {about}"


def controller_term(iso: str, spec: Any) -> str | None:
    """The controller's own name of ``iso`` from a machine's ``controller_kinematics``
    section (``contracts.controller_kinematics.ControllerKinematics``), e.g. "Siemens
    $TC_CARR15[1]"; None when the section names no value holding it."""
    if spec is None or len(iso) != 4:
        return None
    kind, axis = iso[1], iso[3]
    family = {"linuxcnc": "LinuxCNC", "fanuc": "Fanuc", "haas": "Haas", "siemens": "Siemens",
              "heidenhain": "Heidenhain"}.get(spec.family, spec.family)
    # a pivot that moves this axis line alone holds its offset; else one that moves the other
    # rotary axis alone (the relative offset, opposite sign: LinuxCNC's x-offset ≡ −EX0C); a
    # pivot moving both lines together changes nothing the data can see
    ranked = [p for p in spec.params if p.kind == "orientation" and p.component == iso]
    if kind in "XYZ" and axis in "ABC":
        pivots = [p for p in spec.params if p.kind == "pivot" and p.component == kind.lower()
                  and len(p.axes) == 1]
        ranked += [p for p in pivots if p.axes[0] == axis]
        ranked += [p for p in pivots if p.axes[0] != axis]
    return f"{family} {ranked[0].address} ({ranked[0].name})" if ranked else None


def link_label(iso: str, spec: Any = None) -> str:
    """"EX0C — X offset of the C axis line, Siemens $TC_CARR15[1] (x-offset)"."""
    term = controller_term(iso, spec)
    return f"{iso} — {plain_name(iso)}" + (f", {term}" if term else "")
