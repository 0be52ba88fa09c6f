"""Which run may become a machine's drift baseline: not one that FAILed, predates a
compensation written to the controller, or was identified against a model the controller no
longer runs — unless a person overrides it explicitly, with a reason, journaled."""

# The drift of every later run is judged against the baseline's link values. A FAILed run's
# values are the ones the shop wanted gone, and a run from before a compensation was
# identified against the model the controller ran then: against either, the next run of the
# repaired machine shows the repair as "drift" (a 6.1 µm machine judged FAIL on three drift
# reasons). The objections are worded with the run's date and the compensation's number, and
# an override (``--override REASON``, the HMI's Override…) is kept in the baseline's note.

from __future__ import annotations

import time

from daemon.compensation import journal as cj
from daemon.compensation.model import changed_since
from daemon.compensation.names import BadName
from daemon.store import baselines
from daemon.store.journal import Store, StoreError, validate_run_id

MAX_REASON = 300


class BaselineRefused(StoreError):
    """The run cannot be the baseline without an override; the message lists why."""

    def __init__(self, run_id: str, objections: list[str]) -> None:
        super().__init__(f"run {run_id} is not made the drift baseline: "
                         + "; ".join(objections)
                         + " — choose a later run, or override with a reason")
        self.objections = objections


def _when(t: float | None) -> str:
    return time.strftime("%Y-%m-%d %H:%M", time.localtime(t or 0.0))


def objections(store: Store, machine: str, run_id: str) -> list[str]:
    """Why ``run_id`` should not be ``machine``'s baseline ([] when nothing objects). A run
    that is no baseline at all (not finished, ERROR, another machine) raises ``StoreError``
    as ``baselines.confirm`` does: that is not a matter of judgement."""
    validate_run_id(run_id)
    try:
        run = store.run(run_id)
    except (StoreError, KeyError):
        raise StoreError(f"run {run_id} is not in the journal") from None
    out = []
    if run.verdict == "FAIL":
        v = store.verdict(run_id)
        why = "; ".join(v["reasons"])[:160] if v and v["reasons"] else run.summary
        out.append(f"it FAILed ({why})")
    later = [r for r in cj.written(store, machine)
             if r.applied_at is not None and r.applied_at > run.started_at]
    model = changed_since(store, machine, run.started_at)
    if model is not None:
        out.append(f"it started {_when(run.started_at)}, before compensation #{model.id} "
                   f"(written {_when(model.applied_at)} by {model.confirmed_by or 'nobody'}): "
                   "its links were identified against a controller model the controller no "
                   "longer runs")
    elif later:
        first = later[0]
        out.append(f"it started {_when(run.started_at)}, before compensation #{first.id} "
                   f"(written {_when(first.applied_at)}, since {first.state.replace('_', ' ')})"
                   ": a run after the last write is the baseline of the machine as it is")
    return out


def check_override(reason: object, where: str = "--override") -> str:
    """An override's reason: printable text on one line, 3 to ``MAX_REASON`` characters."""
    if not isinstance(reason, str) or len(reason.strip()) < 3:
        raise BadName(f"{where}: give the reason (3 to {MAX_REASON} characters), journaled "
                      "with the baseline")
    if len(reason) > MAX_REASON or any(not ch.isprintable() for ch in reason):
        raise BadName(f"{where}: printable text on one line, at most {MAX_REASON} characters")
    return reason.strip()


def set_baseline(store: Store, machine: str, run_id: str, by: str, note: str = "",
                 override: str | None = None) -> baselines.Baseline:
    """``baselines.confirm`` once nothing objects, or with ``override`` (a person's reason,
    checked by ``check_override``) kept in the note beside the objections it overrode;
    ``BaselineRefused`` otherwise."""
    found = objections(store, machine, run_id)
    if found and override is None:
        raise BaselineRefused(run_id, found)
    if found:  # the reason first: the note is kept to 500 characters
        note = (f"[OVERRIDE by {by}: {override}] " + (f"{note} " if note else "")
                + "— over: " + "; ".join(found))
    return baselines.confirm(store, machine, run_id, by, note)


__all__ = ["MAX_REASON", "BaselineRefused", "check_override", "objections", "set_baseline"]
