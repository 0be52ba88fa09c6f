"""The machine file's controller_kinematics section: the shipped sections load and
mirror the HAL file, every validation error is one ConfigError naming its key, names that could
break out of a comment are refused at load."""

from __future__ import annotations

import copy
import re

import numpy as np
import pytest

from contracts.setup_files import load_controller_kinematics, machine_from_dict
from contracts.yaml_files import ConfigError
from identification.compensation import ControllerParam
from tests.compensation_helpers import (
    HAL,
    LCNC,
    MACHINES,
    THESIS,
    VERTICAL,
    pivot,
    read_doc,
    tilt,
)


def test_shipped_sections_load_and_give_the_math_parameters():
    _, ck = load_controller_kinematics(LCNC)
    assert ck is not None and ck.family == "linuxcnc" and not ck.unattended
    assert (ck.max_change_um, ck.max_change_urad, ck.max_total_um) == (150, 100, 200)
    assert ck.to_math() == [
        ControllerParam("x-rot-point", "pivot", ("B", "C"), "x"),
        ControllerParam("y-rot-point", "pivot", ("B", "C"), "y"),
        ControllerParam("z-rot-point", "pivot", ("B", "C"), "z"),
        ControllerParam("x-offset", "pivot", ("B",), "x"),
        ControllerParam("z-offset", "pivot", ("B",), "z")]
    _, thesis = load_controller_kinematics(THESIS)
    assert thesis is not None and thesis.family == "siemens"
    assert thesis.param("c-tilt-a").to_math() == ControllerParam("c-tilt-a", "orientation",
                                                                 ("C",), "EA0C")
    _, vertical = load_controller_kinematics(VERTICAL)
    assert vertical is not None and [p.address for p in vertical.params] == ["255", "256", "257"]
    # the section is optional
    assert load_controller_kinematics(MACHINES / "seed001_wbzfxyct.yaml")[1] is None


def test_linuxcnc_section_mirrors_the_hal_file_and_the_pivots():
    """Every address is a setp pin of the HAL file with the section's value, and the pivots
    give the machine's B and C points (C at R, B at R + O)."""
    m, ck = load_controller_kinematics(LCNC)
    setp = dict(re.findall(r"^setp (\S+) (\S+)$", HAL.read_text(), flags=re.M))
    for p in ck.params:
        assert float(setp[p.address]) == p.value, p.name
    v = {p.name: p.value for p in ck.params}
    r = np.array([v["x-rot-point"], v["y-rot-point"], v["z-rot-point"]])
    assert np.allclose(m.axes["C"].point_mm, r)
    assert np.allclose(m.axes["B"].point_mm, r + np.array([v["x-offset"], 0, v["z-offset"]]))


def _lcnc_with(params: list[dict] | None = None, **section) -> dict:
    doc = read_doc(LCNC)
    if params is not None:
        doc["controller_kinematics"]["params"] = params
    doc["controller_kinematics"].update(section)
    return doc


def _thesis_with(params: list[dict], family: str = "siemens") -> dict:
    doc = read_doc(THESIS)
    doc["controller_kinematics"] = {"family": family, "params": params}
    return doc


PIN = "xyzbc-trt-kins.x-offset"
BAD = [  # (document, key the message must name, a fragment of the reason)
    (_lcnc_with([pivot("x", PIN, 1, foo=1)]), "controller_kinematics.params.0.foo",
     "unknown key"),
    (_lcnc_with(bogus=1), "controller_kinematics.bogus", "unknown key"),
    (_lcnc_with(guards={"max_change_mm": 1}), "controller_kinematics.guards.max_change_mm",
     "unknown key"),
    (_lcnc_with(guards={"max_change_um": 0}), "controller_kinematics.guards.max_change_um",
     "greater than 0"),
    (_lcnc_with(family="okuma"), "controller_kinematics.family", "linuxcnc"),
    (_lcnc_with([pivot("x", "xyzbc trt", 1)]), "controller_kinematics.params.0.address",
     "HAL pin"),
    (_lcnc_with([pivot("x", "a;b", 1)]), "controller_kinematics.params.0.address", "HAL pin"),
    (_lcnc_with([pivot("x", PIN, 1, axes=["A"])]), "controller_kinematics.params.0.axes",
     "not a rotary axis"),
    (_lcnc_with([pivot("x", PIN, 1, comp="w")]), "controller_kinematics.params.0.component",
     "x, y or z"),
    (_lcnc_with([pivot("x", PIN, 1, axes=["B", "B"])]), "params.0.axes", "twice"),
    (_lcnc_with([{"name": "x", "kind": "pivot", "axes": ["B"], "component": "x",
                  "address": PIN}]), "controller_kinematics.params.0.value", "current value"),
    # a LinuxCNC orientation is a kins pin holding the link in deg (xyzbc_head_kins)
    (_lcnc_with([tilt("t", PIN, "EA0A")]), "controller_kinematics.params.0.component",
     "not an orientation error of this machine"),
    (_lcnc_with([pivot("x", PIN, 1), pivot("x", "a.b", 1)]), "params.1.name", "twice"),
    (_lcnc_with([pivot("x", PIN, 1), pivot("y", PIN, 1)]), "params.1.address", "already"),
    (_lcnc_with([pivot("x", PIN, 1, closing="a.b", closing_value=0)]), "params.0.closing",
     "Siemens"),
    (_lcnc_with([pivot("x", PIN, 1e6)]), "params.0.value", "less than or equal"),
    (_lcnc_with([pivot("x", PIN, float("nan"))]), "params.0.value", "finite"),
    (_thesis_with([pivot("x", "19700.5", 0)], "fanuc"), "params.0.address", "parameter number"),
    (_thesis_with([pivot("x", "#x", 0)], "fanuc"), "params.0.address", "macro variable"),
    (_thesis_with([pivot("x", "P19700", 0)], "fanuc"), "params.0.address", "parameter number"),
    (_thesis_with([pivot("x", "A255", 0)], "haas"), "params.0.address", "setting number"),
    (_thesis_with([tilt("t", "258", "EA0C")], "haas"), "params.0.kind", "no orientation"),
    (_thesis_with([pivot("x", "$TC_CARR4(1)", 0, closing="$TC_CARR18[1]",
                          closing_value=0)]), "params.0.address", "$TC_CARR<n>[<k>]"),
    (_thesis_with([pivot("x", "$TC_CARR13[1]", 0, closing="$TC_CARR18[1]",
                          closing_value=0)]), "params.0.address", "offset vectors"),
    (_thesis_with([pivot("x", "$TC_CARR5[1]", 0, closing="$TC_CARR18[1]",
                          closing_value=0)]), "params.0.address", "y component of l2"),
    (_thesis_with([pivot("x", "$TC_CARR4[1]", 0, closing="$TC_CARR19[1]",
                          closing_value=0)]), "params.0.closing", "y component of l4"),
    (_thesis_with([pivot("x", "$TC_CARR4[1]", 0)]), "params.0.closing", "closes the chain"),
    (_thesis_with([pivot("x", "$TC_CARR4[1]", 0, closing="$TC_CARR18[1]")]),
     "params.0.closing_value", "current value"),
    (_thesis_with([tilt("t", "$TC_CARR11[1]", "EA0C")]), "params.0.vector", "nominal vector"),
    (_thesis_with([tilt("t", "$TC_CARR11[1]", "EA0C", vector=[0, 1, 0])]), "params.0.vector",
     "not along axis C"),
    (_thesis_with([tilt("t", "$TC_CARR10[1]", "EA0C", vector=[0, 0, -1])]),
     "params.0.address", "tilts the y component"),
    (_thesis_with([tilt("t", "$TC_CARR4[1]", "EA0C", vector=[0, 0, -1])]),
     "params.0.address", "rotary-axis vectors"),
    (_thesis_with([tilt("t", "3/SPA", "EA0A")], "heidenhain"), "params.0.component",
     "not an orientation error of this machine"),
    (_thesis_with([tilt("t", "3/SPA", "EB0C", axes=["B"])], "heidenhain"), "params.0.axes",
     "belongs to axis C"),
    (_thesis_with([tilt("t", "3/SPA", "EB0C")], "heidenhain"), "params.0.address", "use SPB"),
    (_thesis_with([pivot("x", "3-X", 0)], "heidenhain"), "params.0.address", "row/column"),
    (_thesis_with([pivot("x", "3/Y", 0)], "heidenhain"), "params.0.address", "use X"),
    (_thesis_with([tilt("t", "19743", "EA0C", vector=[0, 0, 1])], "fanuc"), "params.0.vector",
     "only a Siemens"),
]
INJECTIONS = ["x\n", "x\nM30", "a(b", "a)b", "a;b", "%", "a b", "", "x" * 33]


@pytest.mark.parametrize(("doc", "key", "reason"), BAD,
                         ids=[f"{i}-{b[1].split('.')[-1]}" for i, b in enumerate(BAD)])
def test_every_bad_section_is_one_config_error_naming_the_key(doc, key, reason):
    with pytest.raises(ConfigError) as e:
        machine_from_dict(doc, "m.yaml")
    msg = str(e.value)
    assert msg.startswith("m.yaml: ") and key in msg and reason in msg, msg
    assert "\n" not in msg


@pytest.mark.parametrize("name", INJECTIONS)
def test_names_that_could_break_out_of_a_comment_are_refused_at_load(name):
    with pytest.raises(ConfigError, match=r"params\.0\.name"):
        machine_from_dict(_lcnc_with([pivot(name, PIN, 1)]), "m.yaml")


def test_a_shared_siemens_closing_component_must_agree_on_its_value():
    ok = [pivot("b", "$TC_CARR4[1]", 0, closing="$TC_CARR18[1]", closing_value=0),
          pivot("c", "$TC_CARR15[1]", 0, axes=["C"], closing="$TC_CARR18[1]",
                 closing_value=0)]
    machine_from_dict(_thesis_with(ok), "m.yaml")
    bad = copy.deepcopy(ok)
    bad[1]["closing_value"] = 1
    with pytest.raises(ConfigError, match=r"params\.1\.closing: .*has value 1"):
        machine_from_dict(_thesis_with(bad), "m.yaml")
