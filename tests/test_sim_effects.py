"""One test per effect family: the simulated data change as the effect model says, and a run is
identical for the same seed (different for another)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import brentq

from benchmarks.rigs.sim_helpers import TABLE_B2, g_true, truth_with
from identification.effects import make_effect
from identification.spherefit import fit_spheres
from simulators.controller import VirtualController
from tests.sim_programs import program

POSES = [(0.0, 0.0), (30.0, 60.0), (-45.0, 330.0)]


_PROGRAMS: dict = {}
_RUNS: dict = {}


async def run(errors: dict, seed: int = 0, poses=tuple(POSES), balls=(0, 2)
              ) -> VirtualController:
    """Run the test program (two balls) on a truth; results are cached per (errors, seed)."""
    key = (repr(errors), seed, poses, balls)
    if key in _RUNS:
        return _RUNS[key]
    truth = truth_with(errors)
    if (poses, balls) not in _PROGRAMS:  # the program depends on the nominal geometry only
        _PROGRAMS[(poses, balls)] = program("fanuc", truth, poses, balls=balls)
    text, files = _PROGRAMS[(poses, balls)]
    vc = VirtualController(truth, rng_seed=seed)
    await vc.load_program(text, "fanuc", files)
    await vc.start()
    assert await vc.wait_done(30) == "done", vc.alarm
    _RUNS[key] = vc
    return vc


def latched(vc: VirtualController) -> np.ndarray:
    return np.array([[t.latched[a] for a in "XYZ"] for t in vc.touches])


def centres(vc: VirtualController) -> np.ndarray:
    pts = latched(vc).reshape(-1, 5, 3)
    return fit_spheres(pts, np.full(len(pts), 15.7)).centre_mm


def with_effect(family: str, axis: str | None, params: dict, **options) -> dict:
    return dict(TABLE_B2, effects=[{"family": family, "axis": axis, "params": params,
                                    "options": options}])


def exact_contact(vc: VirtualController, t) -> np.ndarray:
    """Independent root of |tip - ball| = R + r along the move, on the kinematics chain."""
    b, c = t.latched["B"], t.latched["C"]

    def f(s: float) -> float:
        q = (t.start + s * (t.end - t.start))[None]
        return float(np.linalg.norm(g_true(vc.truth, q, b, c, t.ball, t.t_s)[0]) - 15.7)

    s = brentq(f, 0.0, 1.0, xtol=1e-14)
    return t.start + s * (t.end - t.start)


MOTION_CASES = [
    ("linear_scale", "X", {"EXX": 50.0}),
    ("straightness", "Y", {"EXY_q2": 60.0, "EXY_q3": -40.0, "EZY_q2": 30.0, "EZY_q3": 10.0}),
    ("angular_motion", "Z", {f"E{c}Z_q{k}": v for c, v in zip("ABC", (40, -30, 25), strict=True)
                             for k in (1, 2)}),
    ("rotary_positioning", "C", {"ECC_slope": 8.0, "ECC_cos1": 5.0, "ECC_sin1": -4.0,
                                 "ECC_cos2": 3.0, "ECC_sin2": 2.0}),
    ("rotary_error_motion", "B", None),
]


@pytest.mark.parametrize("family,axis,params", MOTION_CASES, ids=[c[0] for c in MOTION_CASES])
async def test_motion_error_effects_act_in_the_chain(family, axis, params):
    if params is None:
        eff = make_effect(family, axis, truth_with({}).machine)
        params = {n: 20.0 for n in eff.param_names}
    base = await run(TABLE_B2)
    vc = await run(with_effect(family, axis, params))
    for t in vc.touches[::7]:
        got = np.array([t.latched[a] for a in "XYZ"])
        assert np.max(np.abs(got - exact_contact(vc, t))) < 1e-6
    assert np.max(np.abs(latched(vc) - latched(base))) > 5e-4  # the effect is visible


async def test_thermal_drift_offsets_the_reading_by_rate_times_time():
    base = await run(TABLE_B2)
    vc = await run(with_effect("thermal_drift", "Y", {"drift_Y_rate": 36.0}))  # µm/h
    t = np.array([r.t_s for r in vc.touches])
    diff = latched(vc) - latched(base)
    assert np.allclose(diff[:, 1], 36.0e-3 * t / 3600.0, atol=1e-9)
    assert np.allclose(diff[:, [0, 2]], 0.0, atol=1e-9)
    assert t[-1] > 30.0  # the run lasts long enough for the drift to matter


async def test_probe_pretravel_pushes_each_latch_along_its_approach():
    base = await run(TABLE_B2)
    p = {f"pretravel_dir{k}": v for k, v in zip(range(1, 6), (1.0, 2.0, 3.0, 4.0, 8.0),
                                                  strict=True)}
    vc = await run(with_effect("probe_pretravel", None, p))
    for t, d in zip(vc.touches, latched(vc) - latched(base), strict=True):
        want = p[f"pretravel_dir{t.touch}"] * 1e-3 * np.asarray(t.direction)
        assert np.allclose(d, want, atol=1e-9)


async def test_gravity_sag_moves_the_measured_centre_as_the_rod_bends():
    base = await run(TABLE_B2)
    vc = await run(with_effect("gravity_sag", None, {"sag_100mm": 2.0}))
    shift = centres(vc) - centres(base)
    truth = vc.truth
    eff = make_effect("gravity_sag", None, truth.machine)
    want = []
    for i in range(0, len(vc.touches), 5):
        t = vc.touches[i]
        b, c = t.latched["B"], t.latched["C"]
        w = eff.ball_offset_mm(np.array([2.0]), truth.context(
            t_s=np.array([0.0]), b_deg=b, c_deg=c, ball=[t.ball]))[0]
        _, rot, _ = truth.chain(np.array([[0, 0, 0, b, c]]))
        # Controller X Y Z follow the tool relative to the workpiece (the machine file's signs
        # make dg/dq the identity), so the centre moves by the foundation-frame displacement.
        want.append(rot[0] @ w)
    want = np.array(want)
    assert np.max(np.abs(shift - want)) < 2e-6
    assert np.max(np.linalg.norm(shift, axis=1)) > 1e-3


async def test_artefact_instability_creeps_one_ball_in_time():
    base = await run(TABLE_B2)
    vc = await run(with_effect("artefact_instability", "B3",
                               {"creep_B3_x": 0.0, "creep_B3_y": 0.0, "creep_B3_z": 360.0},
                               ball_index=2))
    diff = latched(vc) - latched(base)
    for t, d in zip(vc.touches, diff, strict=True):
        if t.ball != 2:
            assert np.allclose(d, 0.0, atol=1e-9)
            continue
        # Every B3 touch lands on the ball where it had crept to at that moment …
        got = np.array([t.latched[a] for a in "XYZ"])
        assert np.max(np.abs(got - exact_contact(vc, t))) < 1e-6
        # … and at B = 0 the pole sees the full creep: 360 µm/h = 0.1 µm/s along C-frame z.
        if t.touch == 5 and t.latched["B"] == 0.0:
            assert d[2] == pytest.approx(1e-4 * t.t_s, rel=1e-6)
    assert np.max(np.abs(diff)) > 2e-3


async def test_noise_is_reproducible_by_seed_and_matches_its_size():
    errs = dict(TABLE_B2, probe={"touch_noise_um": 0.3, "centre_noise_um": [0.6, 0.9, 0.3]})
    one = ((30.0, 60.0),)
    a = await run(errs, seed=7, poses=one)
    _RUNS.clear()  # really run again
    b = await run(errs, seed=7, poses=one)
    c = await run(errs, seed=8, poses=one)
    assert a is not b and np.array_equal(latched(a), latched(b))
    assert not np.array_equal(latched(a), latched(c))
    noise = latched(a) - latched(await run(TABLE_B2, poses=one))
    assert 0.05e-3 < np.std(noise) < 2e-3


async def test_default_noise_gives_the_thesis_centre_repeatability():
    """config/errors/thesis_tableB2.yaml: ball B1 probed 60 times at one pose; the fitted centre
    scatters like thesis §3.4 (0.66 / 0.98 / 0.44 µm)."""
    from simulators.truth import TruthModel

    truth = TruthModel.from_files("config/machines/thesis_wcbxfzyt.yaml",
                                  "config/artefacts/thesis_4ball.yaml",
                                  "config/errors/thesis_tableB2.yaml")
    text, _ = program("fanuc", truth, [(30.0, 60.0)] * 60, balls=[0])
    vc = VirtualController(truth, rng_seed=11)
    await vc.load_program(text, "fanuc")
    await vc.start()
    assert await vc.wait_done(30) == "done", vc.alarm
    std_um = np.std(centres(vc), axis=0, ddof=1) * 1e3
    assert np.all(np.abs(std_um / np.array([0.66, 0.98, 0.44]) - 1) < 0.3), std_um


@pytest.mark.parametrize("family,axis,params", [
    ("straightness", "X", {"EYX_q2": 60.0, "EYX_q3": -40.0, "EZX_q2": 30.0, "EZX_q3": 10.0}),
    ("rotary_positioning", "C", {"ECC_slope": 8.0, "ECC_cos1": 5.0, "ECC_sin1": -4.0,
                                 "ECC_cos2": 3.0, "ECC_sin2": 2.0}),
    ("gravity_sag", None, {"sag_100mm": 2.0}),
    ("probe_pretravel", None, {f"pretravel_dir{k}": float(k) for k in range(1, 6)}),
])
async def test_same_touches_as_the_gap_self_check_simulation(family, axis, params):
    """The gap diagnosis simulates its self-check logs with its own vectorised solver
    (identification/gap/simlog.py); for time-independent effects both must latch the same
    points on the same probing lines, or the self-check would test a different machine."""
    from identification.gap.simlog import Truth, simulate

    def gap_sim(vc: VirtualController, effects: list) -> dict:
        t = vc.truth
        sim = simulate(t.machine, t.artefact, POSES, Truth(
            links=dict(t.links), ball_setup_mm=t.ball_setup_mm, tip_setup_mm=t.tip_setup_mm,
            effects=effects), 3.0, 0.0, 0)
        return {(sim.b_deg[k], sim.c_deg[k], int(sim.ball[k]), int(sim.touch[k])):
                sim.xyz_mm[k] for k in range(len(sim))}

    def ours(vc: VirtualController) -> dict:
        return {(t.latched["B"], t.latched["C"], t.ball, t.touch):
                np.array([t.latched[a] for a in "XYZ"]) for t in vc.touches}

    base, vc = await run(TABLE_B2), await run(with_effect(family, axis, params))
    eff = make_effect(family, axis, vc.truth.machine)
    theirs_base = gap_sim(base, [])
    theirs = gap_sim(vc, [(eff, np.array([params[n] for n in eff.param_names]))])
    # Our probing lines are the program's (4 decimals), theirs exact: compare what the effect
    # changes, where that rounding cancels.
    ob, oe = ours(base), ours(vc)
    assert len(oe) == len(vc.touches)
    for key, p in oe.items():
        d_ours, d_theirs = p - ob[key], theirs[key] - theirs_base[key]
        assert np.max(np.abs(d_ours - d_theirs)) < 1e-6, key
    assert max(np.max(np.abs(p - ob[k])) for k, p in oe.items()) > 5e-4


LOCAL_CASES = [
    ("cyclic_error", "X", {"EXX_cos": 3.0, "EXX_sin": -4.0}, {"period_mm": 25.0}),
    ("local_bump", "Y", {"EZY_height": 8.0},
     {"centre_mm": 60.0, "width_mm": 50.0, "component": "EZY"}),
]


@pytest.mark.parametrize("family,axis,params,options", LOCAL_CASES,
                         ids=[c[0] for c in LOCAL_CASES])
async def test_cyclic_error_and_local_bump_from_the_errors_file(family, axis, params, options):
    """A linear axis' cyclic (pitch) error and local bump, given in the errors file's
    ``effects``: every touch lands on the exact contact of the true chain, and the change
    they make is the one the gap self-check's simulation makes (its truth for them)."""
    from identification.gap.simlog import Truth, simulate

    base = await run(TABLE_B2)
    vc = await run(with_effect(family, axis, params, **options))
    for t in vc.touches[::5]:
        got = np.array([t.latched[a] for a in "XYZ"])
        assert np.max(np.abs(got - exact_contact(vc, t))) < 1e-6
    t = vc.truth
    eff = make_effect(family, axis, t.machine, **options)

    def gap_sim(effects: list) -> dict:
        sim = simulate(t.machine, t.artefact, POSES, Truth(
            links=dict(t.links), ball_setup_mm=t.ball_setup_mm, tip_setup_mm=t.tip_setup_mm,
            effects=effects), 3.0, 0.0, 0)
        return {(sim.b_deg[k], sim.c_deg[k], int(sim.ball[k]), int(sim.touch[k])):
                sim.xyz_mm[k] for k in range(len(sim))}

    theirs_base = gap_sim([])
    theirs = gap_sim([(eff, np.array([params[n] for n in eff.param_names]))])
    moved = 0.0
    for b, v in zip(base.touches, vc.touches, strict=True):
        key = (v.latched["B"], v.latched["C"], v.ball, v.touch)
        d_ours = np.array([v.latched[a] - b.latched[a] for a in "XYZ"])
        assert np.max(np.abs(d_ours - (theirs[key] - theirs_base[key]))) < 1e-6, key
        moved = max(moved, float(np.max(np.abs(d_ours))))
    assert moved > 2e-3  # µm-size: the effect reaches the touches


def test_errors_file_names_a_bad_option_of_a_linear_axis_error():
    from contracts.yaml_files import ConfigError

    with pytest.raises(ConfigError, match=r"effects\[0\] \(cyclic_error/X\).*period_mm"):
        truth_with(with_effect("cyclic_error", "X", {"EXX_cos": 1.0, "EXX_sin": 0.0}))
    with pytest.raises(ConfigError, match=r"effects\[0\] \(local_bump/Z\).*component"):
        truth_with(with_effect("local_bump", "Z", {"EXZ_height": 1.0}, centre_mm=0.0,
                               width_mm=30.0, component="EXY"))
