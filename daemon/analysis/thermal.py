"""The drift search's outcome as the analysis states it: the ``Thermal`` block and the
centres with the fitted drift removed, on which every other analysis of the run is made."""

from __future__ import annotations

from dataclasses import replace

from daemon.analysis.result import Analysis, DriftAxis, Thermal
from daemon.analysis.touch_centres import CentreData
from identification.drift import DriftOutcome


def thermal_block(outcome: DriftOutcome) -> Thermal | None:
    """None when nothing is to be said (no times, a short run, no drift selected)."""
    if outcome.status == "not_separable":
        return Thermal(status=outcome.status, message=outcome.message,
                       inseparable=tuple(outcome.inseparable))
    fit = outcome.fit
    if outcome.status != "selected" or fit is None:
        return None
    tau, tau_u = (fit.tau_s if fit.tau_s is not None else (None, None))
    return Thermal(
        status="selected", message=outcome.message, shape=fit.model.shape,
        span_min=round(fit.span_s / 60.0, 3),
        over_run_um={a: DriftAxis(value=round(v, 4), std=round(u, 4))
                     for a, (v, u) in fit.over_run_um.items()},
        tau_min=None if tau is None else round(tau / 60.0, 3),
        tau_std_min=None if tau_u is None else round(tau_u / 60.0, 3),
        tau_bounded=fit.tau_bounded, bic_gain=round(fit.bic_gain, 3),
        link_inflation=round(fit.link_inflation, 4),
        inseparable=tuple(outcome.inseparable))


def corrected(data: CentreData, outcome: DriftOutcome) -> CentreData:
    """``data`` with the fitted drift taken out of every centre (held-out poses too: they
    were probed between the estimate's, inside the fitted time span)."""
    if outcome.fit is None or data.centres.t_s.size != len(data.centres):
        return data
    c = data.centres
    return replace(data, centres=replace(c, xyz_mm=c.xyz_mm - outcome.fit.centre_drift_mm(c)))


STABILITY_AFTER_DRIFT = (
    "ball centre at its last visit − at its first visit of the same pose, controller X Y Z, "
    "µm, after the fitted TCP drift was removed (what remains: a loose ball, probe drift)")


def with_thermal(analysis: Analysis, block: Thermal | None) -> Analysis:
    """The analysis carrying ``block``; with a drift selected, the revisit shifts it reports
    are those the drift model leaves (the drift itself is in ``thermal``)."""
    if block is None:
        return analysis
    st = analysis.stability
    if block.status == "selected" and st is not None:
        block = replace(block, revisit_residual_um=st.max_shift_um)
        st = replace(st, convention=STABILITY_AFTER_DRIFT)
    return replace(analysis, thermal=block, stability=st)
