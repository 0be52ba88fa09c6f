"""The "sim world" of the compensation tests: a machine file, its truth, a simulated control
probed, identified, and the compensation planned — shared by test_compensate_sim, _heads and
_nutating."""

from __future__ import annotations

import asyncio
import copy
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import yaml

from contracts.controller_kinematics import ControllerKinematics
from contracts.setup_files import load_artefact, load_controller_kinematics, load_machine, load_plan
from daemon.analysis.touch_centres import rows_to_centres
from identification.compensation import (
    CompensationPlan,
    ParamChange,
    apply_changes,
    plan_compensation,
)
from identification.estimate import Estimate, estimate
from programs import compensation
from programs.dialects import get_dialect
from programs.toolpath import build_program
from simulators.controller import VirtualController
from simulators.controller_kinematics import KinematicsStore
from simulators.errors_schema import errors_from_dict
from simulators.offline import touches_to_rows
from simulators.truth import TruthModel

LOOP: list[asyncio.AbstractEventLoop] = []  # one loop per test: a controller's events bind to it


@pytest.fixture
def sim_loop() -> Iterator[None]:
    """A fresh event loop for the test's controllers (use: ``pytestmark`` usefixtures)."""
    LOOP.append(asyncio.new_event_loop())
    yield
    LOOP.pop().close()


def run_program(vc: VirtualController, text: str, dialect: str,
                files: dict[str, str] | None = None) -> str:
    """Load, start and wait for one program; the controller's end state ("done", "alarm")."""
    async def go() -> str:
        await vc.load_program(text, dialect, files)
        await vc.start()
        return await vc.wait_done(60)

    return LOOP[-1].run_until_complete(go())


def feed(vc: VirtualController, dialect: str, text: str) -> None:
    """The rendered write-back into the control as that control takes it."""
    if dialect in ("fanuc", "siemens"):
        assert run_program(vc, text, dialect) == "done", vc.alarm
    elif dialect == "linuxcnc":
        for line in text.splitlines():
            if line.startswith("setp "):
                _, pin, value = line.split()
                vc.halcmd_setp(pin, float(value))
    else:  # operator page: the rows under the header, address old new
        lines = text.splitlines()
        head = next(i for i, ln in enumerate(lines) if ln.split()[:1] in (["setting"],
                                                                            ["row/col"]))
        for line in lines[head + 1:]:
            f = line.split()
            vc.operator_entry(f[0], float(f[3]))


def read_back(spec: ControllerKinematics, store: KinematicsStore) -> list[ParamChange]:
    """The controller model the sim holds: read value − file value, in model units."""
    out = []
    for p in spec.params:
        v = store.read(p.address)
        if p.kind == "pivot":
            delta = v - p.value
        elif spec.family == "siemens":  # from its vector component (an inclined axis too)
            delta = p.held_rad(v) - p.value * 1e-6
        else:
            delta = math.radians(v) - p.value * 1e-6
        out.append(ParamChange(p.name, p.kind, delta, 0.0, True))
    return out


def identify(vc: VirtualController, dialect: str, text: str, files: dict[str, str], machine,
             artefact, run_id: str) -> Estimate:
    """Run the probing program on ``vc`` and identify ``machine``'s links from its touches."""
    state = run_program(vc, text, dialect, files)
    assert state == "done", vc.alarm
    rows = touches_to_rows(vc, run_id)
    data = rows_to_centres(rows, artefact, vc.truth.stylus_radius_mm)
    with np.errstate(all="ignore"):
        return estimate(machine, artefact, data.centres, None)


@dataclass
class SimWorld:
    """A control probed once and its compensation planned (before any write-back)."""

    machine: object
    spec: ControllerKinematics
    artefact: object
    truth: TruthModel
    links_before: dict
    family: str
    text: str
    files: dict[str, str]
    vc: VirtualController
    initial: dict[str, float]  # the control's values before the write-back
    est1: Estimate
    b_deg: np.ndarray
    c_deg: np.ndarray
    params: object
    plan1: CompensationPlan


def sim_world(mpath: Path, epath: Path, ppath: Path, artefact_path: Path, family: str
              ) -> SimWorld:
    """Load the machine (its controller_kinematics of ``family``), plan and errors, build the
    truth, render the probing program, probe the simulated control and plan the compensation."""
    machine, mf = load_machine(mpath)
    _, spec = load_controller_kinematics(mpath)
    assert spec is not None and spec.family == family
    artefact = load_artefact(artefact_path)
    plan = load_plan(ppath)
    truth = TruthModel.build(machine, mf, artefact,
                             errors_from_dict(yaml.safe_load(epath.read_text())))
    links_before = copy.deepcopy(truth.errors.links)
    d = get_dialect(family)
    prog = build_program(machine, mf, artefact, plan)
    text, files = d.render(prog), d.aux_files(prog)
    vc = VirtualController(truth, rng_seed=5, dialect=family)
    assert vc.kinematics is not None
    initial = vc.kinematics.values()
    est1 = identify(vc, family, text, files, machine, artefact, "before")
    b = np.array([p.b_deg for p in plan.poses])
    c = np.array([p.c_deg for p in plan.poses])
    params = spec.to_math()
    plan1 = plan_compensation(machine, artefact, est1, params, b, c)
    return SimWorld(machine, spec, artefact, truth, links_before, family, text, files, vc,
                    initial, est1, b, c, params, plan1)


def compensate_and_check(w: SimWorld) -> tuple[list[str], compensation.CompensationOutput]:
    """Write the planned values to the control, probe again against the controller model it
    now holds, and check what the write-back promised: the truth untouched, each compensable
    link (well identified, nearly all of it compensable) measured at zero within k = 3, the
    compensable distortion down to a tenth, and a rollback restoring every value. Returns the
    compensable links' names and the write-back as rendered."""
    out = compensation.render(w.spec, w.plan1.changes, run_id="R1", machine=w.machine.name)
    feed(w.vc, w.family, out.text)
    assert w.vc.kinematics.values() != w.initial
    assert all(x.address in w.initial for x in w.vc.kinematics.audit)

    model = apply_changes(w.machine, w.params, read_back(w.spec, w.vc.kinematics))
    est2 = identify(w.vc, w.family, w.text, w.files, model, w.artefact, "after")
    assert w.truth.errors.links == w.links_before  # the truth is not what was compensated

    names = list(w.est1.layout.links)
    assert names == list(est2.layout.links)
    p1, est1 = w.plan1, w.est1
    compensable = [k for k, name in enumerate(names)
                   if abs(p1.links_compensable[name]) > 2 * est1.std[k]
                   and abs(p1.links_residual[name]) < 0.1 * abs(p1.links_identified[name])]
    assert compensable, p1.links_compensable
    for k in compensable:
        # est2 = residual + noise2 − noise1 (the changes carry est1's noise): the difference of
        # two independent estimates, so k = 3 on their combined standard uncertainty.
        u = math.hypot(est1.std[k], est2.std[k])
        assert abs(est2.p[k]) <= 3 * u, (names[k], est1.p[k], est2.p[k], u)
    plan2 = plan_compensation(model, w.artefact, est2, w.params, w.b_deg, w.c_deg)
    before, after = p1.distortion_compensable_um[0], plan2.distortion_compensable_um[0]
    assert after <= 0.1 * before, (before, after)

    back = compensation.render(w.spec, p1.changes, run_id="R1", machine=w.machine.name,
                               rollback=True)
    feed(w.vc, w.family, back.text)
    for address, v in w.initial.items():
        assert w.vc.kinematics.read(address) == pytest.approx(v, abs=1e-9), address
    return [names[k] for k in compensable], out
