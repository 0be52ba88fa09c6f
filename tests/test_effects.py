"""The shared effect models (identification/effects.py) do what their equations say."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from contracts.setup_files import load_machine
from identification.effects import (
    FAMILIES,
    EffectContext,
    combine_motion_errors,
    library,
    make_effect,
    workpiece_rotation,
)
from identification.kinematics import ChainState, solve_centre
from identification.spherefit import fit_spheres

CONFIG = Path(__file__).resolve().parents[1] / "config"


@pytest.fixture(scope="module")
def thesis():
    return load_machine(CONFIG / "machines/thesis_wcbxfzyt.yaml")[0]


@pytest.fixture(scope="module")
def vertical():
    return load_machine(CONFIG / "machines/vertical_wcayfxzt.yaml")[0]


def _ctx(n: int, **kw) -> EffectContext:
    base = dict(t_s=np.zeros(n), b_deg=np.zeros(n), c_deg=np.zeros(n), ball=np.zeros(n, int),
                touch=np.ones(n, int), direction=np.tile([0.0, 0.0, -1.0], (n, 1)),
                xyz_mm=np.zeros((n, 3)), ball_nominal_mm=np.zeros((n, 3)),
                rod_length_mm=np.full(n, 100.0))
    base.update(kw)
    return EffectContext(**base)


def test_library_covers_every_family_with_units(thesis):
    lib = library(thesis, ["B1", "B2"])
    assert {e.family for e in lib} == set(FAMILIES)
    for e in lib:
        assert len(e.param_names) == len(e.units) == e.n_params > 0
        assert len(set(e.param_names)) == e.n_params
    with pytest.raises(ValueError, match="unknown effect family"):
        make_effect("spindle_growth", "Z", thesis)
    with pytest.raises(ValueError, match="straightness"):
        make_effect("straightness", "X", thesis, powers=(1, 2))  # linear term = squareness
    with pytest.raises(ValueError, match="rotary_error_motion"):
        make_effect("rotary_error_motion", "C", thesis, orders=(0,))  # order 0 = link error
    with pytest.raises(ValueError, match="linear_scale"):
        make_effect("linear_scale", "B", thesis)
    with pytest.raises(ValueError, match="thermal_drift"):
        make_effect("thermal_drift", "X", thesis, colour="red")
    with pytest.raises(ValueError, match="expected 1 parameters"):
        make_effect("linear_scale", "X", thesis).motion_errors(np.zeros(2))


def test_polynomial_and_harmonic_component_errors(thesis):
    scale = make_effect("linear_scale", "X", thesis).motion_errors(np.array([10.0]))["X"]
    e = scale(np.array([100.0, -200.0]))
    np.testing.assert_allclose(e[:, 0], [1e-3, -2e-3])  # 10 µm/m at 100 mm = 1 µm
    assert not np.any(e[:, 1:])
    st = make_effect("straightness", "Y", thesis)
    assert st.param_names == ("EXY_q2", "EXY_q3", "EZY_q2", "EZY_q3")
    f = st.motion_errors(np.array([100.0, 0.0, 0.0, 1000.0]))["Y"]
    e = f(np.array([500.0]))  # 0.5 m: EXY = 100·0.25 = 25 µm, EZY = 1000·0.125 = 125 µm
    np.testing.assert_allclose(e[0, :3], [25e-3, 0.0, 125e-3])
    rp = make_effect("rotary_positioning", "C", thesis)
    assert rp.param_names[0] == "ECC_slope"
    f = rp.motion_errors(np.array([0.0, 0.0, 5.0, 0.0, 0.0]))["C"]  # sin(1·c) = 5 µrad
    np.testing.assert_allclose(f(np.array([np.pi / 2]))[0], [0, 0, 0, 0, 0, 5e-6], atol=1e-15)
    rem = make_effect("rotary_error_motion", "B", thesis)
    assert rem.param_names[:2] == ("EXB_cos2", "EXB_sin2")  # radial ⟂ to B (y): x and z
    f = rem.motion_errors(np.eye(rem.n_params)[0] * 2.0)["B"]
    # ISO 230-7 fixed frame: −2 µm along fixed x at B = 90°, i.e. along −z of the turned B frame.
    np.testing.assert_allclose(f(np.array([0.0, np.pi / 2]))[:, [0, 2]], [[2e-3, 0], [0, -2e-3]],
                               atol=1e-15)


def test_motion_errors_move_the_centre_through_the_chain(thesis):
    # An X positioning error of 100 µm/m shifts the controller X of a centre at x ≈ 150 mm
    # by the error there, opposite sign through the machine's X sign.
    eff = make_effect("linear_scale", "X", thesis)
    ball = np.array([[150.0, 0.0, 0.0]])
    rot = {"B": np.zeros(1), "C": np.zeros(1)}
    q0 = solve_centre(thesis, rot, ball, ChainState())
    q1 = solve_centre(thesis, rot, ball,
                      ChainState(motion_errors=eff.motion_errors(np.array([100.0]))))
    assert abs(q1[0, 0] - q0[0, 0]) == pytest.approx(150.0 * 100e-6, rel=1e-3)
    both = combine_motion_errors(eff.motion_errors(np.array([1.0])),
                                 eff.motion_errors(np.array([2.0])))
    np.testing.assert_allclose(both["X"](np.array([1000.0]))[0, 0], 3e-3)


def test_gravity_sag_horizontal_and_vertical(thesis, vertical):
    sag = make_effect("gravity_sag", None, thesis)  # horizontal machine: gravity −Y
    ctx = _ctx(3, c_deg=np.array([0.0, 90.0, 0.0]), b_deg=np.array([0.0, 0.0, 45.0]),
               rod_length_mm=np.array([100.0, 100.0, 200.0]))
    d = sag.ball_offset_mm(np.array([2.0]), ctx)
    # In the machine frame the ball always sags 2 µm·(L/100)³ along −Y (rods horizontal).
    r = workpiece_rotation(thesis, ctx.b_deg, ctx.c_deg)
    machine_frame = np.einsum("nij,nj->ni", r, d)
    np.testing.assert_allclose(machine_frame, [[0, -2e-3, 0], [0, -2e-3, 0], [0, -16e-3, 0]],
                               atol=1e-12)
    sag_v = make_effect("gravity_sag", None, vertical)  # vertical trunnion: gravity −Z
    ctx = _ctx(3, b_deg=np.array([0.0, -90.0, -30.0]))  # A tilt; rods vertical at A = 0
    d = sag_v.ball_offset_mm(np.array([2.0]), ctx)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), [0.0, 2e-3, 1e-3], atol=1e-12)


def test_pretravel_uniform_only_changes_the_radius(thesis):
    eff = make_effect("probe_pretravel", None, thesis)
    dirs = np.vstack([np.array([[1, 1, 0], [-1, 1, 0], [-1, -1, 0], [1, -1, 0]]) / np.sqrt(2),
                      [[0, 0, -1]]])
    ctx = _ctx(5, touch=np.arange(1, 6), direction=dirs)
    off = eff.touch_offset_mm(np.full(5, 3.0), ctx)
    np.testing.assert_allclose(off, 3e-3 * dirs)
    r = 15.7
    pts = np.array([10.0, 20.0, 30.0]) - r * dirs  # contact points of a stylus on a ball
    fit0 = fit_spheres(pts[None], r)
    fit1 = fit_spheres((pts + off)[None], r)
    np.testing.assert_allclose(fit1.centre_mm, fit0.centre_mm, atol=1e-9)  # centre unchanged
    assert fit1.radius_dev_um[0] - fit0.radius_dev_um[0] == pytest.approx(-3.0, abs=1e-6)


def test_drift_and_creep_in_time(thesis):
    ctx = _ctx(2, t_s=np.array([0.0, 1800.0]), ball=np.array([1, 1]))
    lin = make_effect("thermal_drift", "Y", thesis)
    np.testing.assert_allclose(lin.touch_offset_mm(np.array([4.0]), ctx)[:, 1], [0, 2e-3])
    exp = make_effect("thermal_drift", "Z", thesis, model="exponential")
    v = exp.touch_offset_mm(np.array([5.0, 0.5]), ctx)[:, 2]
    np.testing.assert_allclose(v, [0.0, 5e-3 * (1 - np.exp(-1.0))])
    creep = make_effect("artefact_instability", "B2", thesis, ball_index=1)
    np.testing.assert_allclose(creep.ball_offset_mm(np.array([2.0, 0.0, -2.0]), ctx)[1],
                               [1e-3, 0, -1e-3])
    other = _ctx(1, t_s=np.array([3600.0]), ball=np.array([0]))
    assert not creep.ball_offset_mm(np.array([2.0, 0.0, -2.0]), other).any()


def test_machine_file_gravity_drives_the_sag_in_simulator_and_library():
    # LinuxCNC xyzbc-trt: a vertical mill whose trunnion B tilts about Y. The heuristic takes
    # B-about-Y for a horizontal machine (gravity −Y); the machine file says −Z.
    import yaml

    from contracts.setup_files import load_artefact, machine_from_dict
    from identification.effects import default_gravity
    from simulators.errors_schema import errors_from_dict
    from simulators.truth import TruthModel

    data = yaml.safe_load((CONFIG / "machines/linuxcnc_xyzbc.yaml").read_text())
    m, mf = machine_from_dict(data, "linuxcnc_xyzbc.yaml")
    assert mf.gravity == [0.0, 0.0, -1.0]
    np.testing.assert_allclose(default_gravity(m), [0.0, -1.0, 0.0])  # what it would guess
    ctx = _ctx(3, b_deg=np.array([0.0, 90.0, 30.0]))
    p = np.array([2.0])
    art = load_artefact(CONFIG / "artefacts/thesis_4ball.yaml")
    errors = errors_from_dict({"effects": [{"family": "gravity_sag",
                                            "params": {"sag_100mm": 2.0}}]})
    sim = TruthModel.build(m, mf, art, errors).effects[0].effect.ball_offset_mm(p, ctx)
    # Rods stand along gravity at B = 0 (no sag), horizontal at B = 90° (full sag).
    np.testing.assert_allclose(np.linalg.norm(sim, axis=1), [0.0, 2e-3, 1e-3], atol=1e-12)
    lib = next(e for e in library(m, art.ids, gravity_dir=mf.gravity)
               if e.family == "gravity_sag")
    np.testing.assert_allclose(lib.ball_offset_mm(p, ctx), sim, atol=1e-15)
    guessed = make_effect("gravity_sag", None, m).ball_offset_mm(p, ctx)
    np.testing.assert_allclose(np.linalg.norm(guessed, axis=1), 2e-3)  # −Y: always sagging
    # Without the key the heuristic still applies; the errors file may still override it.
    data.pop("gravity")
    m2, mf2 = machine_from_dict(data, "no-gravity.yaml")
    assert mf2.gravity is None
    sim2 = TruthModel.build(m2, mf2, art, errors).effects[0].effect.ball_offset_mm(p, ctx)
    np.testing.assert_allclose(sim2, guessed, atol=1e-15)
    over = errors_from_dict({"effects": [{"family": "gravity_sag", "params": {"sag_100mm": 2.0},
                                          "options": {"gravity_dir": [0, -1, 0]}}]})
    sim3 = TruthModel.build(m, mf, art, over).effects[0].effect.ball_offset_mm(p, ctx)
    np.testing.assert_allclose(sim3, guessed, atol=1e-15)


@pytest.mark.parametrize("value,expect", [
    ([0, 0, 0], "gravity: must be a non-zero direction"),
    ([0, -1], "gravity: List should have at least 3 items"),
    ([0, -1, 0, 0], "gravity: List should have at most 3 items"),
    (["down", "x", "y"], "gravity.0: Input should be a valid number"),
    ("down", "gravity: Input should be a valid list"),
    ([0, float("nan"), 1], "gravity.1: Input should be a finite number"),
])
def test_machine_file_gravity_is_validated(value, expect):
    import yaml

    from contracts.setup_files import machine_from_dict
    from contracts.yaml_files import ConfigError

    data = yaml.safe_load((CONFIG / "machines/thesis_wcbxfzyt.yaml").read_text())
    data["gravity"] = value
    with pytest.raises(ConfigError) as e:
        machine_from_dict(data, "m.yaml")
    msg = str(e.value)
    assert msg.startswith("m.yaml: ") and expect in msg and "\n" not in msg
    data["gravity"] = [0, -9.81, 0]  # any length: normalised on load
    assert machine_from_dict(data, "m.yaml")[1].gravity == [0.0, -1.0, 0.0]
    data["gravity_dir"] = [0, -1, 0]  # unknown keys stay errors
    with pytest.raises(ConfigError, match="gravity_dir: unknown key"):
        machine_from_dict(data, "m.yaml")


def test_gravity_dir_option_is_checked(thesis):
    for bad in ([0, 0, 0], [1, 2], ["a", "b", "c"]):
        with pytest.raises(ValueError, match="gravity_dir"):
            make_effect("gravity_sag", None, thesis, gravity_dir=bad)
    sag = make_effect("gravity_sag", None, thesis, gravity_dir=[0, 0, -5])
    ctx = _ctx(1)  # rods along +z: parallel to this gravity, no sag
    np.testing.assert_allclose(sag.ball_offset_mm(np.array([2.0]), ctx), 0.0, atol=1e-15)


def test_cyclic_error_and_local_bump_of_a_linear_axis(thesis):
    from identification.effects import OUTSIDE_FAMILIES

    # outside the diagnosis' library: the simulator and the self-check inject them
    assert set(OUTSIDE_FAMILIES) == {"cyclic_error", "local_bump"}
    assert not set(OUTSIDE_FAMILIES) & set(FAMILIES)
    assert not {e.family for e in library(thesis, ["B1"])} & set(OUTSIDE_FAMILIES)
    cyc = make_effect("cyclic_error", "X", thesis, period_mm=40.0)
    assert cyc.param_names == ("EXX_cos", "EXX_sin") and cyc.units == ("um", "um")
    f = cyc.motion_errors(np.array([3.0, 4.0]))["X"]
    # X has sign −1 (model = −controller): phase 0 at controller X = 0, along the axis
    x_ctrl = np.array([0.0, 10.0, 40.0, -30.0])
    e = f(-x_ctrl)
    want = 3.0 * np.cos(2 * np.pi * x_ctrl / 40) + 4.0 * np.sin(2 * np.pi * x_ctrl / 40)
    np.testing.assert_allclose(e[:, 0], want * 1e-3, atol=1e-15)
    assert not np.any(e[:, 1:])
    bump = make_effect("local_bump", "Y", thesis, centre_mm=50.0, width_mm=40.0,
                       component="EZY")
    assert bump.param_names == ("EZY_height",)
    e = bump.motion_errors(np.array([6.0]))["Y"](np.array([50.0, 60.0, 70.0, 75.0, -50.0]))
    np.testing.assert_allclose(e[:, 2], np.array([6.0, 3.0, 0.0, 0.0, 0.0]) * 1e-3,
                               atol=1e-15)  # raised cosine: half height at a quarter width
    assert not np.any(e[:, [0, 1, 3, 4, 5]])
    for opts, match in (({}, "period_mm is required"), ({"period_mm": -5}, "positive"),
                        ({"period_mm": 40, "component": "EXY"}, "component")):
        with pytest.raises(ValueError, match=match):
            make_effect("cyclic_error", "X", thesis, **opts)
    with pytest.raises(ValueError, match="centre_mm and width_mm are required"):
        make_effect("local_bump", "Z", thesis, width_mm=30)
    with pytest.raises(ValueError, match="local_bump: axis"):
        make_effect("local_bump", "C", thesis, centre_mm=0, width_mm=30)
