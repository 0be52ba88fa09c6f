"""The simulator's warm-up truth (issue 22, simulators/thermal.py): drift and sensor readings from
one thermal state, seen by a simulated run and recovered by the drift-aware analysis."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from contracts.setup_files import load_artefact, load_machine, load_plan
from contracts.yaml_files import ConfigError
from daemon.analysis.identify import analyse_centres
from daemon.analysis.touch_centres import rows_to_centres
from programs.dialects import get_dialect
from programs.toolpath import build_program
from simulators.errors_schema import errors_from_dict
from simulators.offline import run_sync
from simulators.thermal import ThermalState
from simulators.truth import TruthModel

MACHINE = "config/machines/thesis_wcbxfzyt.yaml"
ARTEFACT = "config/artefacts/thesis_4ball.yaml"
PLAN = "config/plans/shift_start_14poses.yaml"


def _errors(thermal: dict | None) -> dict:
    e = yaml.safe_load(Path("config/errors/thesis_tableB2.yaml").read_text())
    if thermal is not None:
        e["thermal"] = thermal
    return e


def test_drift_and_temperatures_come_from_one_state():
    th = ThermalState.from_file(errors_from_dict(_errors({
        "axes": {"Z": {"amplitude_um": 8.0, "tau_s": 900.0, "rise_c": 6.0},
                 "X": {"amplitude_um": -2.0, "tau_s": 1800.0}},
        "start_state": 0.25, "ambient_c": 21.0})).thermal)
    assert np.all(th.drift_mm(0.0) == 0.0)
    for t in (60.0, 900.0, 5000.0):
        s = 1 - 0.75 * np.exp(-t / 900.0)
        assert th.drift_mm(t)[2] * 1e3 == pytest.approx(8.0 * (s - 0.25))
        assert th.temperatures_c(t)["Z"] == pytest.approx(21.0 + 6.0 * s)
        assert th.drift_mm(t)[1] == 0.0
    # the sensor and the drift agree: the drift is the temperature rise times A / rise
    t = 300.0
    rise = th.temperatures_c(t)["Z"] - th.temperatures_c(0.0)["Z"]
    assert th.drift_mm(t)[2] * 1e3 == pytest.approx(rise * 8.0 / 6.0)
    a = ThermalState.amplitude_for(10.0, 223.0, 900.0)
    assert a * -np.expm1(-223.0 / 900.0) == pytest.approx(10.0)


@pytest.mark.parametrize("bad, key", [
    ({"axes": {"B": {"amplitude_um": 1, "tau_s": 60}}}, "axes"),
    ({"axes": {"Z": {"amplitude_um": 1, "tau_s": 0}}}, "tau_s"),
    ({"axes": {"Z": {"amplitude_um": 1}}}, "tau_s"),
    ({"axes": {}, "start_state": 2}, "start_state"),
    ({"axes": {}, "warmth": 1}, "warmth"),
])
def test_a_bad_thermal_section_is_refused_naming_the_key(bad, key):
    with pytest.raises(ConfigError, match=key):
        errors_from_dict(_errors(bad), "e.yaml")


def test_a_simulated_warm_up_is_measured_and_reported():
    m, mf = load_machine(MACHINE)
    a = load_artefact(ARTEFACT)
    plan = load_plan(PLAN)
    text = get_dialect("fanuc").render(build_program(m, mf, a, plan))
    amp = ThermalState.amplitude_for(10.0, 223.0, 900.0)
    truth = TruthModel.build(m, mf, a, errors_from_dict(_errors(
        {"axes": {"Z": {"amplitude_um": amp, "tau_s": 900.0}}})))
    res = run_sync(truth, text, "fanuc", seed=3)
    assert res.state == "done", res.alarm
    data = rows_to_centres(res.rows, a, plan.stylus_radius_mm)
    out = analyse_centres(m, a, data, validate_poses=plan.indices("validate"))
    est_t = data.centres.t_s[~np.isin(data.centres.pose, plan.indices("validate"))]
    want = truth.thermal.over_run_um(est_t.min(), est_t.max())["Z"]
    th = out.thermal
    assert th is not None and th.status == "selected", out.to_json().get("thermal")
    assert 6.0 < want < 11.0
    assert abs(th.over_run_um["Z"].value - want) <= 2.5 * th.over_run_um["Z"].std
    for k, v in out.links.items():  # Table B.2, every link within 3u
        assert abs(v.value - truth.errors.links[k]) <= 3 * v.std, k
