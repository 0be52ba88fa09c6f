"""The cumulative guard: per value, the changes since the last verified baseline (the machine
file's values, moved to a compensation once its verification run confirmed it) plus this one
stay within ``guards.max_cumulative_um`` / ``_urad``."""

from __future__ import annotations

from contracts.controller_kinematics import ControllerKinematics
from daemon.compensation import identified
from daemon.compensation import journal as cj
from daemon.compensation.identified import CompensationRefused
from daemon.compensation.model import controller_model, cumulative_deltas
from daemon.machines.setup import MachineSetup
from daemon.store.journal import Store, StoreError


def _held(setup: MachineSetup, store: Store, spec: ControllerKinematics,
          row: cj.CompensationRow) -> bool:
    """Did ``row``'s verification run confirm it? Its own plan (against the model it ran
    on) would move none of the values ``row`` wrote by more than their expanded uncertainty.
    A compensation that did not hold is no baseline: a second change on top of it is exactly
    the walk the cumulative guard stops."""
    if not row.verify_run_id:
        return False
    try:
        v = store.run(row.verify_run_id)
        model = controller_model(setup, store, before=v.started_at, check_hal=False)
        _, plan = identified.stored_or_computed(setup, store, v.id, model, spec.to_math(),
                                                setup.tolerances.coverage_k)
    except (CompensationRefused, StoreError, ValueError):
        return False
    names = {x.name for x in row.values}
    return all(abs(ch.delta) <= ch.u_expanded or not ch.observable
               for ch in plan.changes if ch.name in names)


def baseline(setup: MachineSetup, store: Store, spec: ControllerKinematics, run_id: str
             ) -> tuple[dict[str, float], str]:
    """The last verified baseline: per parameter the deltas (mm / rad) written up to the last
    compensation (still applied) that its verification run confirmed, else none (the machine
    file's values); and what it is, for messages. ``run_id``'s own compensation verification
    is never a baseline for itself (it wants to change the values: they did not hold)."""
    rows = cj.written(store, setup.name)
    for i in range(len(rows) - 1, max(-1, len(rows) - 6), -1):  # the 5 newest at most
        r = rows[i]
        if r.state == "applied" and r.verify_run_id != run_id and _held(setup, store, spec, r):
            out: dict[str, float] = {}
            for w in rows[:i + 1]:
                for v in w.values:
                    out[v.name] = out.get(v.name, 0.0) + v.delta
            return out, f"compensation #{r.id} verified by run {r.verify_run_id}"
    return {}, "the machine file's values"


def cumulative_refusals(setup: MachineSetup, store: Store, spec: ControllerKinematics,
                        values: list[cj.ValueChange], run_id: str) -> list[str]:
    """Each value's changes since the last verified baseline, this one included, within
    ``guards.max_cumulative_um`` / ``_urad`` (default: the per-change limit); the refusals,
    with the numbers."""
    base, what = baseline(setup, store, spec, run_id)
    now = cumulative_deltas(store, setup.name)
    out = []
    for v in values:
        kind = spec.param(v.name).kind
        limit = (spec.max_cumulative_um or spec.max_change_um) * 1e-3 if kind == "pivot" \
            else (spec.max_cumulative_urad or spec.max_change_urad) * 1e-6
        earlier = now.get(v.name, 0.0) - base.get(v.name, 0.0)
        total = earlier + v.delta
        if abs(total) > limit * (1 + 1e-9):
            f, unit, key = (1e3, "µm", "um") if kind == "pivot" else (1e6, "µrad", "urad")
            out.append(f"{v.name}: {total * f:+.1f} {unit} since the last verified baseline "
                       f"({what}: earlier {earlier * f:+.1f} {unit}, this change "
                       f"{v.delta * f:+.1f} {unit}) is over the cumulative limit "
                       f"{limit * f:.1f} {unit} (guards.max_cumulative_{key}); "
                       "verify that the last compensation held first")
    return out
