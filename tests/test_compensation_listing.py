"""What a person confirms is what the program writes: for every family that compensates, each
address the program (or the operator's page) writes is in the listing with the same value
text, and nothing else is; parsed from the program's own lines, per dialect, for the shipped
sections and random change sets (hypothesis)."""

from __future__ import annotations

import re

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from identification.compensation import ParamChange
from programs.compensation import haas as haas_writer
from programs.compensation import render
from tests.test_compensation_writers import CASES


def _written(case: str, text: str) -> list[tuple[str, str]]:
    """(address, value text) of every write in the program text, read as the control would."""
    lines = text.splitlines()
    if case == "siemens":  # $TC_CARR4[1]=0.012000 ; comment
        return [(m[1], m[2]) for ln in lines if (m := re.match(r"^(\$\w+\[\d+\])=(\S+)", ln))]
    if case == "linuxcnc":  # setp pin value
        return [(m[1], m[2]) for ln in lines if (m := re.match(r"^setp (\S+) (\S+)$", ln))]
    if case == "fanuc":  # G10 L52 / N<param> R<value> / G11, or #<var>=<value>
        out = [(m[1], m[2]) for ln in lines if (m := re.match(r"^N(\d+) R(\S+)$", ln))]
        return out + [(m[1], m[2]) for ln in lines if (m := re.match(r"^(#\d+)=(\S+)$", ln))]
    if case in ("heidenhain", "haas"):  # the page's rows: address, name, old, new[, unit]
        head = next(i for i, ln in enumerate(lines) if re.search(r"\bold\b.*\bnew\b", ln))
        return [(ln.split()[0], ln.split()[3]) for ln in lines[head + 1:] if ln.strip()]
    if case == "haas-program":  # (SETTING <n> <name> OLD <x> NEW <y>)
        return [(m[1], m[2]) for ln in lines
                if (m := re.match(r"^\(SETTING (\S+) \S+ OLD \S+ NEW (\S+)\)$", ln))]
    raise AssertionError(case)


def _check(case: str, out) -> None:
    listed = [(r.address, r.written) for r in out.listing]
    written = _written(case, out.text)
    assert written, out.text  # the parser found the writes
    # fanuc lists macro variables after parameters in this parse: compare as sets and counts
    assert sorted(written) == sorted(listed), (case, out.text, listed)
    assert len({a for a, _ in listed}) == len(listed)  # one entry per address
    for r in out.listing:  # the listing's text names the value as written
        assert f"{r.address} = {r.written}" in r.text()


@pytest.mark.parametrize("rollback", [False, True], ids=["apply", "rollback"])
@pytest.mark.parametrize("case", sorted(CASES))
def test_every_address_written_is_listed_with_its_value(case, rollback):
    section, changes, machine, writer = CASES[case]
    _check(case, writer(section(), changes, run_id="R1", machine=machine, rollback=rollback))


def test_a_siemens_tilt_is_listed_as_the_vector_component_written_with_its_closing():
    """EB0C +26.67 µrad on a C axis along −z is written as $TC_CARR10[1]=-0.000026670 (not
    +26.67 µrad), and a pivot change also moves its closing vector: both listed."""
    section, _, machine, _ = CASES["siemens"]
    out = render(section(), [ParamChange("c-tilt-b", "orientation", 26.67037e-6, 1e-6, True),
                             ParamChange("c-x", "pivot", -0.038063, 0.001, True)],
                 run_id="R1", machine=machine)
    rows = {r.address: r for r in out.listing}
    assert rows["$TC_CARR10[1]"].written == "-0.000026670" and rows["$TC_CARR10[1]"].unit == "1"
    assert rows["$TC_CARR15[1]"].written == "-0.038063"
    assert rows["$TC_CARR18[1]"].written == "0.038063"  # l4 = −l3: the chain stays closed
    assert "$TC_CARR10[1]=-0.000026670" in out.text and "$TC_CARR18[1]=0.038063" in out.text
    _check("siemens", out)


_delta = st.floats(-0.04, 0.04, allow_nan=False).filter(lambda d: abs(d) > 1e-7)
_tilt = st.floats(-80e-6, 80e-6, allow_nan=False).filter(lambda d: abs(d) > 1e-10)
_NAMES = {"linuxcnc": {"x-offset": _delta, "z-offset": _delta, "x-rot-point": _delta},
          "siemens": {"b-x": _delta, "c-x": _delta, "c-y": _delta, "b-z": _delta,
                      "c-tilt-a": _tilt, "c-tilt-b": _tilt, "b-tilt-c": _tilt},
          "fanuc": {"b-x": _delta, "c-y": _delta, "c-tilt-b": _tilt},
          "heidenhain": {"b-x": _delta, "c-y": _delta, "c-tilt-b": _tilt},
          "haas": {"mrzp-x": _delta, "mrzp-y": _delta}}


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data(), case=st.sampled_from(sorted(_NAMES)), rollback=st.booleans())
def test_random_change_sets_list_what_they_write(data, case, rollback):
    section = CASES[case][0]()
    names = data.draw(st.lists(st.sampled_from(sorted(_NAMES[case])), min_size=1,
                               unique=True), label="names")
    changes = []
    for n in names:
        kind = section.param(n).kind
        changes.append(ParamChange(n, kind, data.draw(_NAMES[case][n], label=n), 1e-6, True))
    out = render(section, changes, run_id="R1", machine=CASES[case][2], rollback=rollback)
    _check(case, out)
    if case == "haas":
        _check("haas-program", haas_writer.program(section, changes, run_id="R1",
                                                   machine=CASES[case][2], rollback=rollback))
