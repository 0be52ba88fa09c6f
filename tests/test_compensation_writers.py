"""The compensation writers: every family's text for a fixed change set and its
rollback, the values in the control's units, the HAL-file patch, number formatting, and
injection attempts through run ids, machine names and addresses."""

from __future__ import annotations

import dataclasses
import math
import os
import re
from pathlib import Path

import numpy as np
import pytest

from contracts.controller_kinematics import ControllerKinematics
from contracts.setup_files import load_controller_kinematics
from daemon.store.journal import RUN_ID_PATTERN
from identification.compensation import ParamChange
from programs.compensation import CompensationError, fixed, fmt_value, patch_hal_file, render
from programs.compensation import haas as haas_writer
from programs.compensation.common import RUN_ID, Value
from tests.compensation_helpers import HAL, LCNC, THESIS, VERTICAL, pivot, section_of, tilt

# not under tests/golden: tests/test_gcode_golden.py wants exactly its own files there
GOLDEN = Path(__file__).resolve().parent / "data" / "compensation"
REGEN = "RUMBA_REGEN_COMPENSATION"  # set to 1 to rewrite the golden files (then review the diff)
CHANGES = [ParamChange("x-offset", "pivot", 0.106, 0.004, True),
           ParamChange("z-rot-point", "pivot", -1e-7, 0.001, True),
           ParamChange("y-rot-point", "pivot", -0.0, 0.001, True)]
THESIS_CHANGES = [ParamChange("b-x", "pivot", 0.012, 0.001, True),
                  ParamChange("c-x", "pivot", -0.005, 0.001, True),
                  ParamChange("c-tilt-a", "orientation", 12e-6, 1e-6, True),
                  ParamChange("b-tilt-c", "orientation", -3e-6, 1e-6, True)]
OTHER_CHANGES = [ParamChange("b-x", "pivot", 0.012, 0.001, True),
                 ParamChange("c-y", "pivot", -1e-7, 0.001, True),
                 ParamChange("c-tilt-b", "orientation", -20e-6, 1e-6, True)]
HAAS_CHANGES = [ParamChange("mrzp-y", "pivot", 0.02, 0.001, True),
                ParamChange("mrzp-x", "pivot", -0.0015, 0.001, True)]


def _other(family: str, addresses: tuple[str, str, str]) -> ControllerKinematics:
    return section_of(THESIS, family, [pivot("b-x", addresses[0], 100.5),
                                     pivot("c-y", addresses[1], -2, axes=["C"], comp="y"),
                                     tilt("c-tilt-b", addresses[2], "EB0C", value=5)])


CASES = {  # golden name → (section, changes, machine name, writer)
    "linuxcnc": (lambda: load_controller_kinematics(LCNC)[1], CHANGES, "linuxcnc-xyzbc", render),
    "siemens": (lambda: load_controller_kinematics(THESIS)[1], THESIS_CHANGES,
                "thesis-wcbxfzyt", render),
    "fanuc": (lambda: _other("fanuc", ("19700", "#500", "19743")), OTHER_CHANGES,
              "thesis-wcbxfzyt", render),
    "heidenhain": (lambda: _other("heidenhain", ("3/X", "4/Y", "5/SPB")), OTHER_CHANGES,
                   "thesis-wcbxfzyt", render),
    "haas": (lambda: load_controller_kinematics(VERTICAL)[1], HAAS_CHANGES, "vertical-wcayfxzt",
             render),
    "haas-program": (lambda: load_controller_kinematics(VERTICAL)[1], HAAS_CHANGES,
                     "vertical-wcayfxzt", haas_writer.program),
}


@pytest.mark.parametrize("rollback", [False, True], ids=["apply", "rollback"])
@pytest.mark.parametrize("case", sorted(CASES))
def test_every_family_matches_its_golden_output(case, rollback):
    section, changes, machine, writer = CASES[case]
    out = writer(section(), changes, run_id="20260101T000000Z-0a0a", machine=machine,
                 rollback=rollback)
    path = GOLDEN / f"{case}{'-rollback' if rollback else ''}.txt"
    if os.environ.get(REGEN) == "1":
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(out.text, encoding="utf-8")
    assert out.text == path.read_text(encoding="utf-8"), f"{path.name}: set {REGEN}=1, review"
    assert out.filename.startswith("rollback" if rollback else "compensation")
    assert ("ROLLBACK" in out.text) is rollback
    assert not re.search(r"\d[eE][+-]?\d", out.text)  # never exponent notation
    forward = writer(section(), changes, run_id="R1", machine=machine)
    if rollback:  # the same values the other way round
        assert [(v.address, v.old, v.new) for v in out.values] == \
            [(v.address, v.new, v.old) for v in forward.values]


def test_written_values_are_old_plus_change_in_the_controls_units():
    _, ck = load_controller_kinematics(LCNC)
    out = render(ck, CHANGES, run_id="R1", machine="linuxcnc-xyzbc")
    assert out.filename == "compensation-linuxcnc-xyzbc-R1.hal"
    assert out.values[0] == Value("x-offset", "xyzbc-trt-kins.x-offset", 12.5, 12.606, "mm")
    assert "setp xyzbc-trt-kins.x-offset 12.606000\n" in out.text
    _, th = load_controller_kinematics(THESIS)
    sv = {v.address: v for v in render(th, THESIS_CHANGES, run_id="R1", machine="m").values}
    assert sv["$TC_CARR18[1]"] == Value("b-x+c-x", "$TC_CARR18[1]", 0.0, -0.007, "mm")  # closed
    assert sv["$TC_CARR11[1]"].new == pytest.approx(12e-6, abs=1e-12)
    fv = render(_other("fanuc", ("19700", "#500", "19743")), OTHER_CHANGES, run_id="R1",
                machine="m").values
    assert fv[2].unit == "deg" and fv[2].old == pytest.approx(round(math.degrees(5e-6), 6))
    assert fv[2].new == pytest.approx(round(math.degrees(-15e-6), 6))
    hv = haas_writer.program(CASES["haas"][0](), HAAS_CHANGES, run_id="R1", machine="m")
    assert all(ln.startswith(("(", "%", "O09990", "M30")) for ln in hv.text.splitlines())


def test_patch_hal_file_changes_only_the_setp_values_and_rolls_back():
    _, ck = load_controller_kinematics(LCNC)
    text = HAL.read_text(encoding="utf-8")
    changes = [ParamChange("x-offset", "pivot", 0.106, 0.004, True),
               ParamChange("x-rot-point", "pivot", -0.0123456, 0.001, True)]
    out = render(ck, changes, run_id="R1", machine="linuxcnc-xyzbc")
    patched = patch_hal_file(text, out.values)
    old_lines, new_lines = text.splitlines(keepends=True), patched.splitlines(keepends=True)
    assert len(old_lines) == len(new_lines)
    diff = [(a, b) for a, b in zip(old_lines, new_lines, strict=True) if a != b]
    assert diff == [("setp xyzbc-trt-kins.x-offset 12.5\n",
                     "setp xyzbc-trt-kins.x-offset 12.606000\n"),
                    ("setp xyzbc-trt-kins.x-rot-point 0\n",
                     "setp xyzbc-trt-kins.x-rot-point -0.012346\n")]
    back = render(ck, changes, run_id="R1", machine="linuxcnc-xyzbc", rollback=True)
    restored = patch_hal_file(patched, back.values)
    assert [float(x) for x in re.findall(r"^setp \S+ (\S+)$", restored, flags=re.M)] == \
        [float(x) for x in re.findall(r"^setp \S+ (\S+)$", text, flags=re.M)]
    # applying twice is refused: the file no longer holds the old value
    with pytest.raises(CompensationError, match=re.escape(
            "x-offset is 12.606000, expected the old value 12.500000")):
        patch_hal_file(patched, out.values)


def test_patch_hal_file_refuses_a_missing_or_duplicated_pin():
    text = HAL.read_text(encoding="utf-8")
    v = [Value("x-offset", "xyzbc-trt-kins.x-offset", 12.5, 12.6, "mm")]
    missing = text.replace("setp xyzbc-trt-kins.x-offset 12.5\n", "")
    with pytest.raises(CompensationError, match=re.escape(
            "no 'setp xyzbc-trt-kins.x-offset' line")):
        patch_hal_file(missing, v)
    twice = text + "setp xyzbc-trt-kins.x-offset 12.5\n"
    with pytest.raises(CompensationError, match="appears 2 times"):
        patch_hal_file(twice, v)
    # a pin whose name only starts like the address is another pin
    other = missing + "setp xyzbc-trt-kins.x-offset2 12.5\n"
    with pytest.raises(CompensationError, match="no 'setp"):
        patch_hal_file(other, v)
    # CRLF and a trailing comment are kept
    crlf = "setp  xyzbc-trt-kins.x-offset\t12.5 # B\r\n"
    assert patch_hal_file(crlf, v) == "setp  xyzbc-trt-kins.x-offset\t12.600000 # B\r\n"


@pytest.mark.parametrize(("link", "vector"), [("EA0C", (0, 0, -1)), ("EB0C", (0, 0, -1)),
                                              ("EA0B", (0, -1, 0)), ("EC0B", (0, -1, 0)),
                                              ("EB0C", (0, 0, 1))])
def test_siemens_axis_vector_component_is_the_tilted_vector(link, vector):
    """The written component equals the exactly rotated nominal vector's (to first order)."""
    theta = 40e-6
    i = "ABC".index(link[1])
    c, s = math.cos(theta), math.sin(theta)
    rot = {0: [[1, 0, 0], [0, c, -s], [0, s, c]], 1: [[c, 0, s], [0, 1, 0], [-s, 0, c]],
           2: [[c, -s, 0], [s, c, 0], [0, 0, 1]]}[i]
    tilted = np.asarray(rot) @ np.asarray(vector, float)
    j = int(np.argmax(np.abs(tilted - vector)))
    address = f"$TC_CARR{(7 if link[3] == 'B' else 10) + j}[1]"
    ck = section_of(THESIS, "siemens", [tilt("t", address, link, vector=list(vector))])
    out = render(ck, [ParamChange("t", "orientation", theta, 1e-6, True)], run_id="R1",
                 machine="m")
    assert out.values[0].address == address
    assert out.values[0].new == pytest.approx(tilted[j], abs=1e-12)


def test_linuxcnc_orientation_pin_holds_the_link_in_degrees():
    """xyzbc_head_kins: a tilt pin holds the link in deg; the section's value
    is µrad; rollback writes the old value back."""
    pin = "xyzbc-head-kins.ea0c-deg"
    ck = section_of(LCNC, "linuxcnc", [tilt("t", pin, "EA0C", value=10.0)])
    change = [ParamChange("t", "orientation", 40e-6, 1e-6, True)]
    (v,) = render(ck, change, run_id="R1", machine="m").values
    assert (v.address, v.unit) == (pin, "deg")
    assert v.old == pytest.approx(math.degrees(10e-6), abs=1e-6)
    assert v.new == pytest.approx(math.degrees(50e-6), abs=1e-6)
    assert f"setp {pin} 0.002865\n" in render(ck, change, run_id="R1", machine="m").text
    (r,) = render(ck, change, run_id="R1", machine="m", rollback=True).values
    assert (r.old, r.new) == (v.new, v.old)


# ------------------------------------------------------------------ numbers, changes, headers


@pytest.mark.parametrize(("v", "text"), [(1e-7, "0.000000"), (-1e-7, "0.000000"),
                                         (-0.0, "0.000000"), (1e-5, "0.000010"),
                                         (-12.5, "-12.500000"), (99999.1234564, "99999.123456"),
                                         (5e-7, "0.000000"), (6e-7, "0.000001")])
def test_numbers_have_fixed_decimals_and_no_exponent(v, text):
    assert fixed(v) == text == fmt_value(v, "mm") == fmt_value(v, "deg")
    assert fmt_value(v / 1000, "1") == f"{v / 1000:.9f}".replace("-0.000000000", "0.000000000")
    assert fmt_value(1e-10, "1") == "0.000000000" and fmt_value(-1.2e-8, "1") == "-0.000000012"


@pytest.mark.parametrize("v", [math.nan, math.inf, -math.inf, 1e300, 1e6])
def test_values_that_are_not_finite_or_absurd_are_refused(v):
    with pytest.raises(CompensationError):
        fixed(v)
    _, ck = load_controller_kinematics(LCNC)
    with pytest.raises(CompensationError):
        render(ck, [ParamChange("x-offset", "pivot", v, 0.001, True)], run_id="R1", machine="m")


@pytest.mark.parametrize(("change", "match"), [
    (ParamChange("w-offset", "pivot", 0.1, 0.001, True), "not a parameter"),
    (ParamChange("x-offset", "orientation", 0.1, 0.001, True), "kind"),
])
def test_changes_must_match_the_section(change, match):
    _, ck = load_controller_kinematics(LCNC)
    with pytest.raises(CompensationError, match=match):
        render(ck, [change], run_id="R1", machine="m")
    with pytest.raises(CompensationError, match="changed twice"):
        render(ck, [CHANGES[0], CHANGES[0]], run_id="R1", machine="m")


@pytest.mark.parametrize("family", ["linuxcnc", "fanuc", "haas", "siemens", "heidenhain"])
@pytest.mark.parametrize(("run_id", "machine"), [
    ("R1\nM30", "m"), ("R1)", "m"), ("R1;x", "m"), ("%", "m"), ("../x", "m"), ("-x", "m"),
    ("R1", "m\n"), ("R1", "m(x)"), ("R1", "m;x"), ("R1", "m%"), ("R1", "a b")])
def test_run_ids_and_machine_names_that_could_inject_are_refused(family, run_id, machine):
    ck = {"linuxcnc": lambda: load_controller_kinematics(LCNC)[1],
          "siemens": lambda: load_controller_kinematics(THESIS)[1],
          "haas": lambda: load_controller_kinematics(VERTICAL)[1],
          "fanuc": lambda: section_of(THESIS, "fanuc", [pivot("b-x", "19700", 0)]),
          "heidenhain": lambda: section_of(THESIS, "heidenhain",
                                           [pivot("b-x", "3/X", 0)])}[family]()
    name = ck.params[0].name
    with pytest.raises(CompensationError, match="invalid"):
        render(ck, [ParamChange(name, "pivot", 0.001, 0.001, True)], run_id=run_id,
               machine=machine)


@pytest.mark.parametrize("address", ["x-offset\nM30", "a(b)", "a;b", "a b", "%"])
def test_a_section_built_by_hand_cannot_inject_an_address(address):
    _, ck = load_controller_kinematics(LCNC)
    bad = dataclasses.replace(ck, params=(dataclasses.replace(ck.params[3], address=address),))
    with pytest.raises(CompensationError, match="not plain"):
        render(bad, [CHANGES[0]], run_id="R1", machine="m")


def test_run_id_rule_is_the_stores():
    assert RUN_ID.pattern == RUN_ID_PATTERN
