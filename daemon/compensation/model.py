"""The controller's kinematic model as rumba believes it: the machine file's
``controller_kinematics`` section changed by every compensation the journal says was written,
and, for a LinuxCNC on this PC, the live pins that must agree with it."""

from __future__ import annotations

import numpy as np

from contracts.controller_kinematics import ControllerKinematics, controller_kinematics
from daemon.compensation import journal as cj
from daemon.compensation.identified import CompensationRefused
from daemon.compensation.listing import expected_values
from daemon.machines.setup import MachineSetup
from daemon.store.journal import Store
from identification.compensation import Guards, ParamChange, apply_changes
from identification.kinematics import Machine


class ControllerModelError(Exception):
    """The controller's kinematics disagree with the journal (changed outside rumba)."""


def spec_of(setup: MachineSetup) -> ControllerKinematics | None:
    """The machine file's ``controller_kinematics`` section, checked against the machine; None
    when the machine file has none."""
    section = getattr(setup.machine_file, "controller_kinematics", None)
    if section is None:
        return None
    return controller_kinematics(section, setup.machine, f"machine {setup.name}")




def check_family(setup: MachineSetup, spec: ControllerKinematics) -> None:
    """The machine file's controller addresses are of the configured controller (
    $TC_CARR values proposed for a machine configured as Fanuc), else ``CompensationRefused``
    naming both."""
    want = str(setup.dialect)  # a controller-kinematics family is a dialect name
    if spec.family != want:
        example = spec.params[0].address if spec.params else ""
        raise CompensationRefused(
            f"machine {setup.name} is configured as {setup.dialect} (daemon.yaml dialect) but "
            f"its machine file's controller_kinematics holds {spec.family} addresses "
            f"({example}, …): give the {want} control's own parameters in the machine file "
            "(or the right dialect); nothing is proposed")


def guards_of(spec: ControllerKinematics) -> Guards:
    return Guards(spec.max_change_um * 1e-3, spec.max_change_urad * 1e-6,
                  spec.max_total_um * 1e-3, spec.min_effect_um * 1e-3)


def unit_of(kind: str) -> tuple[str, float]:
    """The section's unit of a value and its factor from the model's (mm, rad)."""
    return ("mm", 1.0) if kind == "pivot" else ("urad", 1e6)


def is_local_linuxcnc(setup: MachineSetup, spec: ControllerKinematics | None) -> bool:
    """LinuxCNC on this PC: the link's ``mode: local``, or linuxcncrsh on a loopback host."""
    from daemon.hosts import is_loopback

    link = setup.link
    if spec is None or spec.family != "linuxcnc" or getattr(link, "transport", "") != "linuxcnc":
        return False
    return link.mode == "local" or is_loopback(link.host)


# ------------------------------------------------------------------------- controller model


def cumulative_deltas(store: Store, machine: str, before: float | None = None
                      ) -> dict[str, float]:
    """Per parameter: the sum of the deltas (mm / rad) written to the controller so far."""
    out: dict[str, float] = {}
    for row in cj.written(store, machine, before):
        for v in row.values:
            out[v.name] = out.get(v.name, 0.0) + v.delta
    return out


def controller_model(setup: MachineSetup, store: Store, *, before: float | None = None,
                     check_hal: bool = True) -> Machine:
    """The model the controller runs: the machine file's, changed by every compensation
    written before ``before`` (default: all). For a LinuxCNC on this PC the live kinematics
    pins must equal the journal's values, else ``ControllerModelError``."""
    spec = spec_of(setup)
    if spec is None:
        return setup.machine
    params = spec.to_math()
    deltas = cumulative_deltas(store, setup.name, before)
    if check_hal and before is None and is_local_linuxcnc(setup, spec):
        check_hal_agrees(setup, spec, store)
    changes = [ParamChange(p.name, p.kind, deltas[p.name], 0.0, True, "journal")
               for p in params if abs(deltas.get(p.name, 0.0)) > 0.0]
    return apply_changes(setup.machine, params, changes) if changes else setup.machine


def changed_since(store: Store, machine: str, started_at: float) -> cj.CompensationRow | None:
    """The compensation written after ``started_at`` that left the controller's model other
    than it was when the run started (applied, not undone by a rollback since), or None."""
    before, now = cumulative_deltas(store, machine, started_at), cumulative_deltas(store, machine)
    if all(abs(before.get(k, 0.0) - now.get(k, 0.0)) < 1e-12 for k in {*before, *now}):
        return None
    written = cj.written(store, machine)
    later = [r for r in written if (r.applied_at or 0.0) >= started_at] or written
    return later[-1] if later else None


def check_hal_agrees(setup: MachineSetup, spec: ControllerKinematics, store: Store) -> None:
    from drivers.linuxcnc import halkins

    # the section's (and journal's) orientation values are µrad of the held link; the kins
    # pin holds it in deg (xyzbc_head_kins, programs/compensation/linuxcnc.py)
    want = {n: (a, v if spec.param(n).kind == "pivot" else float(np.degrees(v * 1e-6)))
            for n, (a, v) in expected_values(spec, store, setup.name).items()}
    try:
        got = halkins.read_pins([a for a, _ in want.values()])
    except halkins.HalError as e:
        if spec.read_back == "when_written" and not cj.written(store, setup.name):
            # rumba never wrote to this controller: its model is the machine file's, as before
            # compensation existed; the pins cannot be read (no HAL access for this user).
            # ``read_back: required`` makes readable pins a condition of every run and write.
            return
        raise ControllerModelError(f"machine {setup.name}: cannot read the kinematics pins: "
                                   f"{e}") from None
    bad = [f"{a} = {got[a]:g} (journal/machine file: {v:g})" for a, v in want.values()
           if not halkins.agrees(got[a], v)]
    if bad:
        raise ControllerModelError(
            f"machine {setup.name}: LinuxCNC's kinematics differ from rumba's journal: "
            f"{'; '.join(bad)} — someone changed the kinematics outside rumba; restore them "
            "or record the change before identifying against this controller")
