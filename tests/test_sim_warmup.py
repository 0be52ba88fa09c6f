"""The simulator's warm-up truth (simulators/thermal.py): drift and sensor readings from
one thermal state, seen by a simulated run and recovered by the drift-aware analysis."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml

from benchmarks.rigs.sim_helpers import TABLE_B2, truth_with
from contracts.setup_files import load_artefact, load_machine, load_plan
from contracts.yaml_files import ConfigError
from daemon.analysis.identify import analyse_centres
from daemon.analysis.touch_centres import rows_to_centres
from programs.dialects import get_dialect
from programs.toolpath import build_program
from simulators.controller import VirtualController as VC
from simulators.errors_schema import errors_from_dict
from simulators.offline import run_sync
from simulators.thermal import ThermalState
from simulators.truth import TruthModel
from tests.sim_programs import program

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


async def test_the_warm_up_runs_on_across_programs_on_one_controller():
    """Two programs in a row on one simulated controller (a re-probe round, the next run): the
    second meets the machine as warm as the first left it — its touches drift and its sensors
    read on the warm-up curve from the first program's end — while its touch times and its
    machine time count from its own start, as a control's program clock does."""
    warm = {"axes": {"Z": {"amplitude_um": 9.0, "tau_s": 120.0, "rise_c": 6.0},
                     "X": {"amplitude_um": -3.0, "tau_s": 200.0, "rise_c": 2.0}},
            "ambient_c": 21.0}
    hot = truth_with({**TABLE_B2, "thermal": warm})
    cold = replace(hot, thermal=None)  # the same machine without the warm-up: the drift apart
    text, _ = program("fanuc", hot, [(0.0, 0.0), (-30.0, 90.0)])
    vc, twin = VC(hot, rng_seed=5), VC(cold, rng_seed=5)  # one noise sequence for both
    ends: list[float] = []
    latched: list[np.ndarray] = []
    times: list[list[float]] = []
    for k in range(2):
        for c in (vc, twin):
            await c.load_program(text, "fanuc")
            await c.start()
        if k == 1:  # started, no block run yet: the machine as the first program left it
            assert vc.machine_time_s == 0.0 and vc.thermal_time_s == ends[0]
            assert vc.sensor_temperatures() == hot.thermal.temperatures_c(ends[0])
        assert await vc.wait_done(30) == "done" and await twin.wait_done(30) == "done"
        ends.append(vc.machine_time_s)
        times.append([t.t_s for t in vc.touches])
        assert times[-1] == [t.t_s for t in twin.touches]  # the warm-up moves no axis
        latched.append(np.array([[t.latched[a] for a in "XYZ"] for t in vc.touches])
                       - np.array([[t.latched[a] for a in "XYZ"] for t in twin.touches]))
    t1, t2 = ends
    assert len(times[1]) == 40 and t1 > 10.0 and t2 == pytest.approx(t1, rel=0.05)
    assert times[1][0] < times[0][-1]  # the program clock restarted …
    assert vc.thermal_time_s == pytest.approx(t1 + t2, rel=1e-12)  # … the thermal one ran on
    for k, start in enumerate((0.0, t1)):  # each touch's drift at the machine's clock
        want = np.array([hot.thermal.drift_mm(start + t) for t in times[k]])
        np.testing.assert_allclose(latched[k], want, rtol=0, atol=1e-9)
    # it continues: the second program's first touch drifts past the first's last, Z warming
    assert latched[1][0, 2] > latched[0][-1, 2] > latched[0][0, 2] + 1e-3
    assert latched[1][0, 2] * 1e3 > 0.5 * 9.0 * (1 - np.exp(-t1 / 120.0))
    # the sensors and the variables a DNC program prints: the state at the machine's time
    now = hot.thermal.temperatures_c(t1 + t2)
    assert vc.sensor_temperatures() == pytest.approx(now, rel=1e-12)
    assert vc.variables["#593"] == pytest.approx(now["Z"], rel=1e-12)
    assert now["Z"] > hot.thermal.temperatures_c(t1)["Z"] + 0.1
