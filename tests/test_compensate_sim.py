"""Compensation through the simulator, every dialect: the rendered write-back reaches
the simulated control's kinematic values (never its truth), and a re-run identified against the
controller model it now holds measures the compensable links at zero."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from contracts.setup_files import load_artefact, load_machine
from simulators.controller import VirtualController
from simulators.errors_schema import errors_from_dict
from simulators.truth import TruthModel
from tests.sim_world import compensate_and_check, run_program, sim_loop, sim_world  # noqa: F401

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


pytestmark = pytest.mark.usefixtures("sim_loop")


@pytest.mark.parametrize("dialect", ["fanuc", "haas", "linuxcnc", "siemens", "heidenhain"])
def test_compensation_through_the_simulator(tmp_path: Path, dialect: str) -> None:
    mpath, epath, ppath = _machine_file(tmp_path, dialect)
    compensate_and_check(sim_world(mpath, epath, ppath, ARTEFACT, dialect))


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
    assert (run_program(fanuc_vc, text, "fanuc")) == "alarm"
    assert why in (fanuc_vc.alarm or "")
    assert fanuc_vc.kinematics.values() == before


def test_macro_variables_and_parameters_read_and_write_the_model(
        fanuc_vc: VirtualController) -> None:
    text = "%\nO1\n#500=#500+0.25\n#100=#501\nG10 L52\nN19700 R100.6\nG11\nM30\n%\n"
    assert (run_program(fanuc_vc, text, "fanuc")) == "done", fanuc_vc.alarm
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
    assert (run_program(s, "$TC_CARR5[1]=1.0\nM30\n", "siemens")) == "alarm"
    assert "$TC_CARR5[1]" in (s.alarm or "")
    assert (run_program(s, "R1=$TC_CARR4[1]+1\n$TC_CARR4[1]=R1\nM30\n",
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
