"""Compensation write-back for the nutating (inclined-axis) table: the SINUMERIK
type P carrier whose v1 is the 45° B vector (a B tilt about R0·x moves two of its components),
a Heidenhain kinematics table and Fanuc 19700-series values, through the simulator: the rendered
write-back reaches the control, a re-run identified against the controller model it now holds
measures the compensable links at zero, rollback restores every value."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from contracts.setup_files import load_controller_kinematics
from contracts.yaml_files import ConfigError
from identification.compensation import ParamChange
from programs import compensation
from tests.sim_world import compensate_and_check, sim_loop, sim_world  # noqa: F401

CFG = Path(__file__).resolve().parents[1] / "config"
MACHINE = CFG / "machines/nutating_wcbyfxzt.yaml"
ERRORS = CFG / "errors/nutating_wcbyfxzt.yaml"
PLAN = CFG / "plans/nutating_12poses.yaml"
ARTEFACT = CFG / "artefacts/vertical_4ball.yaml"  # as tests/test_head_families_e2e.py
GUARDS = {"max_change_um": 200, "max_change_urad": 100, "max_total_um": 400}
# The shipped Siemens section's values re-addressed (section order): a Heidenhain kinematics
# table row per axis (X Y Z, SPA/SPB/SPC: the row of the inclined B follows the fixed 45° turn,
# so its spatial angles are about R0·x, R0·z as the links), Fanuc 19700-series real parameters.
_ROWS = {"B": 3, "C": 4}
_FANUC = ["19700", "19701", "19703", "19705", "19741", "19742", "19743", "19744"]
# What the probing sees of the control's values (the rank computation):
# EX0C by the C line's x; EY0C and the B line's offsets are absorbed by the setup.
OBSERVABLE = {"c-x", "b-tilt-a", "b-tilt-c", "c-tilt-a", "c-tilt-b"}


def _section(family: str) -> dict:
    data = yaml.safe_load(MACHINE.read_text(encoding="utf-8"))
    params = []
    for i, p in enumerate(data["controller_kinematics"]["params"]):
        q = {k: p[k] for k in ("name", "kind", "component") if k in p}
        if p["kind"] == "pivot":
            q.update(axes=p["axes"], value=p["value"])
            row = f"{_ROWS[p['axes'][0]]}/{p['component'].upper()}"
        else:
            row = f"{_ROWS[p['component'][-1]]}/SP{p['component'][1]}"
        q["address"] = row if family == "heidenhain" else _FANUC[i]
        params.append(q)
    return {"family": family, "guards": GUARDS, "params": params}


def _machine_file(tmp: Path, family: str) -> Path:
    if family == "siemens":
        return MACHINE
    data = yaml.safe_load(MACHINE.read_text(encoding="utf-8"))
    data["controller_kinematics"] = _section(family)
    out = tmp / f"nutating_{family}.yaml"
    out.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return out


pytestmark = pytest.mark.usefixtures("sim_loop")


@pytest.mark.parametrize("family", ["siemens", "heidenhain", "fanuc"])
def test_nutating_compensation_through_the_simulator(tmp_path: Path, family: str) -> None:
    w = sim_world(_machine_file(tmp_path, family), ERRORS, PLAN, ARTEFACT, family)
    assert {ch.name for ch in w.plan1.changes if ch.observable} == OBSERVABLE
    assert all(ch.note and ch.delta == 0.0 for ch in w.plan1.changes if not ch.observable)
    got, out = compensate_and_check(w)
    if family == "siemens":  # the inclined B's EA0B moves v1's y and z together
        written = {v.address for v in out.values}
        assert {"$TC_CARR8[1]", "$TC_CARR9[1]", "$TC_CARR7[1]"} <= written, written
    # the injected EA0B (18 µrad) and EC0B (−23 µrad) are among them: the inclined axis' tilts
    assert {"EA0B", "EC0B", "EX0C"} <= set(got) <= {"EX0C", "EA0C", "EB0C", "EA0B", "EC0B"}, got


def test_an_inclined_axis_vector_is_the_exactly_tilted_vector() -> None:
    """Each component written for a B tilt equals the nominal v1 rotated exactly by θ about the
    tilt's axis in the machine frame (R0·x for EA0B, R0·z for EC0B), to first order."""
    _, spec = load_controller_kinematics(MACHINE)
    assert spec is not None
    theta = 40e-6
    for name, axis in (("b-tilt-a", (1.0, 0.0, 0.0)), ("b-tilt-c", (0.0, -0.5**0.5, 0.5**0.5))):
        p = spec.param(name)
        assert p.tilt_axis == pytest.approx(axis)
        k = np.asarray(axis)
        kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        rot = np.eye(3) + math.sin(theta) * kx + (1 - math.cos(theta)) * kx @ kx
        tilted = rot @ np.asarray(p.vector)
        out = compensation.render(spec, [ParamChange(name, "orientation", theta, 1e-6, True)],
                                  run_id="R1", machine="m")
        assert len(out.values) == (2 if name == "b-tilt-a" else 1)
        for v in out.values:
            j = int(v.address[8]) - 7  # $TC_CARR7..9: x y z of v1
            assert v.new == pytest.approx(tilted[j], abs=2e-9), (name, v)
            assert p.held_rad(v.new) == pytest.approx(theta, rel=1e-4) if v.address == \
                p.address else True


@pytest.mark.parametrize("edit, key, reason", [
    ({"also": None}, "params.4.also", "also moves the z component"),
    ({"address": "$TC_CARR7[1]", "also": ["$TC_CARR9[1]"]}, "params.4.address",
     "tilts the y, z component"),
    ({"also": ["$TC_CARR12[1]"]}, "params.4.also.0", "not a component of the axis vector"),
    ({"also": ["$TC_CARR8[1]"]}, "params.4.also.0", "twice"),
    ({"vector": [0, 0.70710678118654752, 0.6]}, "params.4.vector", "unit vector"),
    ({"vector": [0, -1, 0]}, "params.4.vector", "not along axis B"),
    ({"also": ["$TC_CARR7[1]"]}, "params.4.also.0", "is its x component"),
])
def test_a_bad_inclined_axis_vector_is_one_config_error(tmp_path: Path, edit: dict, key: str,
                                                        reason: str) -> None:
    data = yaml.safe_load(MACHINE.read_text(encoding="utf-8"))
    p = data["controller_kinematics"]["params"][4]
    assert p["name"] == "b-tilt-a"
    for k, v in edit.items():
        if v is None:
            p.pop(k)
        else:
            p[k] = v
    path = tmp_path / "m.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    with pytest.raises(ConfigError) as e:
        load_controller_kinematics(path)
    msg = str(e.value)
    assert "m.yaml" in msg and key in msg and reason in msg, msg
