"""Words for people, defined once for the report, the PDF, the HMI and the CLI: what to do after
each verdict, and durations written the way a shop floor reads them."""

from __future__ import annotations

import math

ADVICE = {
    "PASS": "Machine fit for production: release it. No action needed.",
    "WARN": "The machine may run, but a value is near its limit or drifting: tell the "
            "maintenance or metrology engineer today and plan a check before it fails.",
    "FAIL": "Do not machine precision parts: the geometry is out of tolerance. Call maintenance "
            "to re-calibrate the axes named below, then run the check again.",
    "ERROR": "No statement on the machine: the measurement could not be trusted or the run did "
             "not finish. Clean the balls and the stylus, check the artefact is tight and the "
             "machine is warm, fix the cause named below, then run the check again.",
}
"""Plain-language next step per verdict, for the operator at the machine."""


def advice(status: str | None) -> str:
    """The next step for a verdict (``None`` or an unknown status: the run gave none)."""
    return ADVICE.get(status or "ERROR", ADVICE["ERROR"])


def duration_text(seconds: float | None) -> str:
    """``"42 s"`` below two minutes, ``"3.8 min"`` below two hours, ``"5.1 h"`` beyond: never
    ``"0 min"`` for a short span, and the same words in every place that states one."""
    if seconds is None or not math.isfinite(seconds):
        return "—"
    s = max(0.0, float(seconds))
    if s < 120:
        return f"{s:.0f} s"
    if s < 7200:
        return f"{s / 60:.1f} min"
    return f"{s / 3600:.1f} h"
