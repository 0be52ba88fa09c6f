"""Compensation through the simulator, every dialect (issue 13): the rendered write-back reaches
the simulated control's kinematic values (never its truth), and a re-run identified against the
controller model it now holds measures the compensable links at zero."""

from __future__ import annotations

import asyncio
import copy
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from contracts.controller_kinematics import ControllerKinematics, siemens_tilt
from contracts.setup_files import load_artefact, load_controller_kinematics, load_machine, load_plan
from daemon.analysis.touch_centres import rows_to_centres
from identification.compensation import ParamChange, apply_changes, plan_compensation
from identification.estimate import estimate
from programs import compensation
from programs.dialects import get_dialect
from programs.toolpath import build_program
from simulators.controller import VirtualController
from simulators.controller_kinematics import KinematicsStore
from simulators.errors_schema import errors_from_dict
from simulators.offline import touches_to_rows
from simulators.truth import TruthModel

CFG = Path(__file__).resolve().parents[1] / "config"
THESIS = CFG / "machines/thesis_wcbxfzyt.yaml"
LCNC = CFG / "machines/linuxcnc_xyzbc.yaml"
ARTEFACT = CFG / "artefacts/thesis_4ball.yaml"
GUARDS = {"max_change_um": 200, "max_change_urad": 100, "max_total_um": 400}
# The thesis machine's B/C pivots and tilts at each control's address (the Siemens section ships).
_PIVOTS = [("b-x", ["B", "C"], "x"), ("b-z", ["B", "C"], "z"), ("c-x", ["C"], "x"),
           ("c-y", ["C"], "y")]
_TILTS = [("b-tilt-a", "EA0B"), ("b-tilt-c", "EC0B"), ("c-tilt-a", "EA0C"), ("c-tilt-b", "EB0C")]
_ADDRESSES = {
    "fanuc": (["19700", "19702", "#500", "#501"], ["19741", "19742", "19743", "19744"]),
    "heidenhain": (["3/X", "3/Z", "4/X", "4/Y"], ["3/SPA", "3/SPC", "4/SPA", "4/SPB"]),
    "haas": (["255", "257", "258", "259"], []),
}
VALUES = [100.5, -40.0, 0.0, -2.0]  # the control's current pivot values (mm)


def _machine_file(tmp: Path, dialect: str) -> tuple[Path, Path, Path]:
    """(machine file, errors file, plan) whose controller_kinematics family is ``dialect``."""
    if dialect == "linuxcnc":
        return LCNC, CFG / "errors/linuxcnc_xyzbc.yaml", CFG / "plans/linuxcnc_7poses.yaml"
    errors, plan = CFG / "errors/thesis_tableB2.yaml", CFG / "plans/thesis_annexB_14poses.yaml"
    if dialect == "siemens":
        return THESIS, errors, plan
    data = yaml.safe_load(THESIS.read_text(encoding="utf-8"))
    pivots, tilts = _ADDRESSES[dialect]
    params = [{"name": n, "kind": "pivot", "axes": axes, "component": comp, "address": a,
               "value": v}
              for (n, axes, comp), a, v in zip(_PIVOTS, pivots, VALUES, strict=True)]
    params += [{"name": n, "kind": "orientation", "component": comp, "address": a}
               for (n, comp), a in zip(_TILTS, tilts, strict=False)]
    data["controller_kinematics"] = {"family": dialect, "guards": GUARDS, "params": params}
    path = tmp / f"thesis_{dialect}.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path, errors, plan


LOOP: list[asyncio.AbstractEventLoop] = []  # one loop per test: a controller's events bind to it


@pytest.fixture(autouse=True)
def _loop():
    LOOP.append(asyncio.new_event_loop())
    yield
    LOOP.pop().close()


def _run(vc: VirtualController, text: str, dialect: str,
         files: dict[str, str] | None = None) -> str:
    async def go() -> str:
        await vc.load_program(text, dialect, files)
        await vc.start()
        return await vc.wait_done(60)

    return LOOP[-1].run_until_complete(go())


def _program(vc: VirtualController, text: str, dialect: str) -> None:
    state = (_run(vc, text, dialect))
    assert state == "done", vc.alarm


def _feed(vc: VirtualController, dialect: str, text: str) -> None:
    """The rendered write-back into the control as that control takes it."""
    if dialect in ("fanuc", "siemens"):
        _program(vc, text, dialect)
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


def _read_back(spec: ControllerKinematics, store: KinematicsStore) -> list[ParamChange]:
    """The controller model the sim holds: read value − file value, in model units."""
    out = []
    for p in spec.params:
        v = store.read(p.address)
        if p.kind == "pivot":
            delta = v - p.value
        elif spec.family == "siemens":
            assert p.vector is not None
            delta = v / siemens_tilt(p.component, p.vector)[1] - p.value * 1e-6
        else:
            delta = math.radians(v) - p.value * 1e-6
        out.append(ParamChange(p.name, p.kind, delta, 0.0, True))
    return out


def _identify(vc, dialect, text, files, machine, artefact, run_id):
    state = (_run(vc, text, dialect, files))
    assert state == "done", vc.alarm
    rows = touches_to_rows(vc, run_id)
    data = rows_to_centres(rows, artefact, vc.truth.stylus_radius_mm)
    with np.errstate(all="ignore"):
        return estimate(machine, artefact, data.centres, None)


@pytest.mark.parametrize("dialect", ["fanuc", "haas", "linuxcnc", "siemens", "heidenhain"])
def test_compensation_through_the_simulator(tmp_path: Path, dialect: str) -> None:
    mpath, epath, ppath = _machine_file(tmp_path, dialect)
    machine, mf = load_machine(mpath)
    _, spec = load_controller_kinematics(mpath)
    assert spec is not None and spec.family == dialect
    artefact = load_artefact(ARTEFACT)
    plan = load_plan(ppath)
    truth = TruthModel.build(machine, mf, artefact,
                             errors_from_dict(yaml.safe_load(epath.read_text())))
    links_before = copy.deepcopy(truth.errors.links)
    d = get_dialect(dialect)
    prog = build_program(machine, mf, artefact, plan)
    text, files = d.render(prog), d.aux_files(prog)
    vc = VirtualController(truth, rng_seed=5, dialect=dialect)
    assert vc.kinematics is not None
    initial = vc.kinematics.values()

    est1 = _identify(vc, dialect, text, files, machine, artefact, "before")
    b = np.array([p.b_deg for p in plan.poses])
    c = np.array([p.c_deg for p in plan.poses])
    params = spec.to_math()
    plan1 = plan_compensation(machine, artefact, est1, params, b, c)
    out = compensation.render(spec, plan1.changes, run_id="R1", machine=machine.name)
    _feed(vc, dialect, out.text)
    assert vc.kinematics.values() != initial
    assert all(w.address in initial for w in vc.kinematics.audit)

    model = apply_changes(machine, params, _read_back(spec, vc.kinematics))
    est2 = _identify(vc, dialect, text, files, model, artefact, "after")
    assert truth.errors.links == links_before  # the truth is not what was compensated

    names = list(est1.layout.links)
    assert names == list(est2.layout.links)
    compensable = [k for k, name in enumerate(names)
                   if abs(plan1.links_compensable[name]) > 2 * est1.std[k]
                   and abs(plan1.links_residual[name]) < 0.1 * abs(plan1.links_identified[name])]
    assert compensable, plan1.links_compensable
    for k in compensable:
        # est2 = residual + noise2 − noise1 (the changes carry est1's noise): the difference of
        # two independent estimates, so k = 3 on their combined standard uncertainty.
        u = math.hypot(est1.std[k], est2.std[k])
        assert abs(est2.p[k]) <= 3 * u, (names[k], est1.p[k], est2.p[k], u)
    plan2 = plan_compensation(model, artefact, est2, params, b, c)
    before, after = plan1.distortion_compensable_um[0], plan2.distortion_compensable_um[0]
    assert after <= 0.1 * before, (before, after)

    back = compensation.render(spec, plan1.changes, run_id="R1", machine=machine.name,
                               rollback=True)
    _feed(vc, dialect, back.text)
    for address, v in initial.items():
        assert vc.kinematics.read(address) == pytest.approx(v, abs=1e-9), address


@pytest.fixture
def fanuc_vc(tmp_path: Path) -> VirtualController:
    mpath, epath, _ = _machine_file(tmp_path, "fanuc")
    machine, mf = load_machine(mpath)
    truth = TruthModel.build(machine, mf, load_artefact(ARTEFACT),
                             errors_from_dict(yaml.safe_load(epath.read_text())))
    return VirtualController(truth, dialect="fanuc")


@pytest.mark.parametrize("block, why", [
    ("N19999 R1.000000", "19999 is not available"),
    ("N19700 R100", "decimal point"),
    ("N19700 P1 R1.0", "axis-type"),
])
def test_a_rejected_parameter_alarms(fanuc_vc: VirtualController, block: str, why: str) -> None:
    before = fanuc_vc.kinematics.values()
    text = f"%\nO9990\nG10 L52\n{block}\nG11\nM30\n%\n"
    assert (_run(fanuc_vc, text, "fanuc")) == "alarm"
    assert why in (fanuc_vc.alarm or "")
    assert fanuc_vc.kinematics.values() == before


def test_macro_variables_and_parameters_read_and_write_the_model(
        fanuc_vc: VirtualController) -> None:
    text = "%\nO1\n#500=#500+0.25\n#100=#501\nG10 L52\nN19700 R100.6\nG11\nM30\n%\n"
    assert (_run(fanuc_vc, text, "fanuc")) == "done", fanuc_vc.alarm
    assert fanuc_vc.kinematics.read("#500") == pytest.approx(0.25)
    assert fanuc_vc.variables["#100"] == pytest.approx(-2.0)
    assert fanuc_vc.kinematics.read("19700") == pytest.approx(100.6)
    assert [w.source for w in fanuc_vc.kinematics.audit] == ["#500=", "G10 L52"]


def test_values_outside_the_declared_addresses_are_refused(tmp_path: Path) -> None:
    vcs = {}
    for dialect in ("siemens", "linuxcnc", "heidenhain", "haas"):
        mpath, epath, _ = _machine_file(tmp_path, dialect)
        machine, mf = load_machine(mpath)
        truth = TruthModel.build(machine, mf, load_artefact(ARTEFACT),
                                 errors_from_dict(yaml.safe_load(epath.read_text())))
        vcs[dialect] = VirtualController(truth, dialect=dialect)
    s = vcs["siemens"]
    assert (_run(s, "$TC_CARR5[1]=1.0\nM30\n", "siemens")) == "alarm"
    assert "$TC_CARR5[1]" in (s.alarm or "")
    assert (_run(s, "R1=$TC_CARR4[1]+1\n$TC_CARR4[1]=R1\nM30\n",
                            "siemens")) == "done", s.alarm
    assert s.kinematics.read("$TC_CARR4[1]") == pytest.approx(1.0)
    with pytest.raises(KeyError):
        vcs["linuxcnc"].halcmd_setp("xyzbc-trt-kins.w-offset", 1.0)
    with pytest.raises(KeyError):
        vcs["heidenhain"].operator_entry("9/X", 1.0)
    with pytest.raises(KeyError):
        vcs["haas"].operator_entry("999", 1.0)
    with pytest.raises(KeyError):  # an operator page is not halcmd
        vcs["haas"].halcmd_setp("255", 1.0)
    assert all(not vc.kinematics.audit for k, vc in vcs.items() if k != "siemens")
