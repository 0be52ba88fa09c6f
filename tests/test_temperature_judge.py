"""The judge on temperature channels: outside the range or changed beyond the
limit over the run → WARN with the numbers, never FAIL; a limited channel that gave nothing →
WARN (the limit could not be checked); an unlimited channel changes nothing."""

from __future__ import annotations

import dataclasses

import pytest

from daemon.analysis.judge import judge
from daemon.analysis.result import Analysis, LinkError
from daemon.machines.tolerances import Limit, Tolerances

TOL = Tolerances(default_translation_um=Limit(warn=60, fail=120))


def analysis(**temps: dict) -> Analysis:
    return Analysis(machine="m", links={"EX0C": LinkError(5.0, 1.0, "um")},
                    temperatures=temps or None)


def t(start: float, end: float, lo: float | None = None, hi: float | None = None) -> dict:
    return {"source": "x", "start_c": start, "end_c": end, "change_c": end - start,
            "min_c": min(start, end) if lo is None else lo,
            "max_c": max(start, end) if hi is None else hi, "errors": []}


@pytest.mark.parametrize(("limits", "temps", "status", "why"), [
    ({"spindle": (None, None, 2.0)}, {"spindle": t(20.0, 21.5)}, "PASS", None),
    ({"spindle": (None, None, 2.0)}, {"spindle": t(20.0, 23.1)}, "WARN",
     "temperature change spindle over the run = +3.10 °C: machine not thermally stable: "
     "|change| > 2 °C (20.0 → 23.1 °C)"),
    ({"spindle": (None, None, 2.0)}, {"spindle": t(23.1, 20.0)}, "WARN", "|change| > 2 °C"),
    ({"spindle": (18.0, 26.0, None)}, {"spindle": t(25.0, 27.5)}, "WARN",
     "temperature spindle = +27.50 °C: machine outside its temperature range [18, 26] °C"),
    ({"spindle": (18.0, None, None)}, {"spindle": t(17.2, 19.0)}, "WARN",
     "temperature spindle = +17.20 °C: machine outside its temperature range [18, ] °C"),
    ({"spindle": (None, None, 2.0)}, {}, "WARN",
     "temperature spindle: temperature limit not checked: channel not read (no reading in "
     "this run)"),
    ({"spindle": (None, None, 2.0)},
     {"spindle": {"source": "x", "start_c": None, "end_c": None, "change_c": None,
                  "min_c": None, "max_c": None, "errors": ["opcua: BadNodeIdUnknown"]}},
     "WARN", "channel not read (opcua: BadNodeIdUnknown)"),
    ({}, {"spindle": t(10.0, 40.0)}, "PASS", None),
])
def test_temperature_limits_warn_with_the_reason(limits, temps, status, why):
    j = judge(analysis(**temps), dataclasses.replace(TOL, temperatures=limits))
    assert j.status == status, j.reasons
    if why:
        assert any(why in r for r in j.reasons), j.reasons


def test_a_temperature_never_fails_a_run_and_never_hides_a_link_fail():
    hot = {"spindle": t(20.0, 45.0)}
    tol = dataclasses.replace(TOL, temperatures={"spindle": (15.0, 30.0, 1.0)})
    assert judge(analysis(**hot), tol).status == "WARN"
    bad = dataclasses.replace(analysis(**hot), links={"EX0C": LinkError(200.0, 1.0, "um")})
    j = judge(bad, tol)
    assert j.status == "FAIL" and any("EX0C" in r for r in j.reasons)
    assert any("temperature change spindle" in r for r in j.reasons)
