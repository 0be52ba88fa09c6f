"""The simulator's truth with the 18 motion errors of the linear axes (errors file
``motion_errors``): the functions are the documented Legendre series, a random smooth draw
holds its amplitudes and its seed, a probing run on the virtual controller measures them, bad
keys are refused naming file and key, and the LinuxCNC HAL probe refuses them plainly."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml

from contracts.setup_files import load_artefact, load_machine, load_plan
from contracts.yaml_files import ConfigError
from daemon.analysis.touch_centres import rows_to_centres
from programs.generate import generate
from simulators.errors_schema import errors_from_dict, load_errors
from simulators.hal_probe import write_spec
from simulators.offline import run_sync
from simulators.truth import TruthModel

ROOT = Path(__file__).resolve().parent.parent
MACHINE = ROOT / "config" / "machines" / "thesis_wcbxfzyt.yaml"
ARTEFACT = ROOT / "config" / "artefacts" / "thesis_4ball.yaml"
PLAN = ROOT / "config" / "plans" / "thesis_ch3_7poses.yaml"


def truth(errors: dict, seed: int = 0) -> TruthModel:
    m, mf = load_machine(MACHINE)
    return TruthModel.build(m, mf, load_artefact(ARTEFACT), errors_from_dict(errors), seed)


def tip_in_workpiece(t: TruthModel, xyz: np.ndarray) -> np.ndarray:
    q = np.zeros((len(xyz), 5))
    q[:, :3] = xyz
    tip, rot, org = t.chain(q)
    return np.einsum("sji,sj->si", rot, tip - org)


def test_a_given_series_moves_the_tip_as_documented():
    """EYX = 8·P2(u) µm over X ∈ [−300, 300] (u = x/300) and EZZ = 5·P1 µm: the tool tip in the
    workpiece frame moves by exactly that (X carries the table on this machine: the table's
    straightness in y is the tip's −y relative to it; Z carries the tool: +z), and beyond the
    range the series continues as its tangent line."""
    t = truth({"motion_errors": {"X": {"range_mm": [-300, 300], "EYX": {"legendre": [0, 0, 8]}},
                                 "Z": {"range_mm": [-250, 550], "EZZ": {"legendre": [0, 5]}}}})
    t0 = truth({})
    x = np.array([-300.0, -150.0, 0.0, 150.0, 300.0, 350.0])
    pts = np.stack([x, np.zeros_like(x), np.full_like(x, 150.0)], axis=1)
    d_um = (tip_in_workpiece(t, pts) - tip_in_workpiece(t0, pts)) * 1e3
    u = x / 300.0
    p2 = np.where(np.abs(u) <= 1, 8 * (3 * u**2 - 1) / 2, 8 + 8 * 3 * (u - 1))  # tangent: P2'(1)=3
    np.testing.assert_allclose(d_um[:, 1], -p2, atol=1e-6)
    z_u = (2 * 150.0 - (-250) - 550) / 800
    np.testing.assert_allclose(d_um[:, 2], 5 * z_u, atol=1e-6)
    np.testing.assert_allclose(d_um[:, 0], 0.0, atol=1e-6)


def test_random_smooth_holds_its_amplitudes_and_seed():
    spec = {"motion_errors": {"random_smooth": {"seed": 11, "translation_um": [5, 20],
                                                "rotation_urad": [10, 30], "order": 4}}}
    a, b = truth(spec, seed=0), truth(spec, seed=5)  # the draw is the file's seed, not --seed
    c = truth({"motion_errors": {"random_smooth": {"seed": 12, "translation_um": [5, 20],
                                                   "rotation_urad": [10, 30]}}})
    assert sorted(a.motion) == sorted(f"E{s}{ax}" for s in "XYZABC" for ax in "XYZ")
    for name, f in a.motion.items():
        x = np.linspace(f.lo_mm, f.hi_mm, 801)
        peak = np.max(np.abs(f(x)))
        lo, hi = (10, 30) if name[1] in "ABC" else (5, 20)
        assert lo - 1e-9 <= peak <= hi + 1e-9, (name, peak)
        assert (f.lo_mm, f.hi_mm) == tuple(a.machine.axes[name[2]].travel)
        assert f.legendre == b.motion[name].legendre
        assert f.legendre != c.motion[name].legendre


def test_a_probing_run_measures_the_motion_errors():
    """The 7-pose chapter-3 plan run on the virtual controller (no noise): every fitted centre
    is where the truth with its motion errors puts it, within the shear the slopes of the
    errors give the five touches in controller coordinates (METHOD.md §7, "the sphere fit is
    not innocent": measured 0.33 µm at slopes of ~1e-4), and the motion errors moved the
    centres by tens of µm."""
    m, mf = load_machine(MACHINE)
    art = load_artefact(ARTEFACT)
    plan = load_plan(PLAN)
    text = generate(m, mf, art, plan, "fanuc").text
    spec = {"motion_errors": {"random_smooth": {"seed": 3, "translation_um": [10, 20],
                                                "rotation_urad": [20, 30]}}}
    out = {}
    for name, errs in (("map", spec), ("none", {})):
        t = truth(errs)
        res = run_sync(t, text, "fanuc", seed=0)
        assert res.state == "done", res.alarm
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            c = rows_to_centres(res.rows, art, plan.stylus_radius_mm).centres
        want = np.array([t.centre_ctrl(int(b), bb, cc) for b, bb, cc
                         in zip(c.ball, c.b_deg, c.c_deg, strict=True)])
        assert np.max(np.abs(c.xyz_mm - want)) * 1e3 < 0.6
        out[name] = c.xyz_mm
    moved = np.max(np.abs(out["map"] - out["none"])) * 1e3
    assert moved > 10.0, moved


@pytest.mark.parametrize("text, key", [
    ("X: {EXY: {legendre: [1]}}", "motion_errors: X.EXY: unknown key"),
    ("X: {EXX: {legendre: [1], order: 2}}", "motion_errors: X.EXX.order: unknown key"),
    ("W: {EXX: {legendre: [1]}}", "motion_errors.W: unknown key"),
    ("X: {range_mm: [300, -300]}", "motion_errors.X.range_mm"),
    ("X: {EXX: {legendre: [.nan]}}", "motion_errors: X.EXX.legendre.0"),
    ("random_smooth: {seed: 1, amplitude_um: 5}", "motion_errors.random_smooth.amplitude_um"),
    ("random_smooth: {axes: [X, B]}", "motion_errors.random_smooth.axes"),
    ("random_smooth: {range_mm: {X: [1, 1]}}", "motion_errors.random_smooth.range_mm"),
])
def test_bad_motion_errors_name_file_and_key(tmp_path, text, key):
    path = tmp_path / "errors.yaml"
    path.write_text(f"motion_errors:\n  {text}\n")
    with pytest.raises(ConfigError) as e:
        load_errors(path)
    msg = str(e.value)
    assert msg.startswith(f"{path}: ") and key in msg and "\n" not in msg, msg


def test_the_hal_probe_refuses_motion_errors_plainly(tmp_path):
    t = truth({"motion_errors": {"Y": {"EXY": {"legendre": [0, 0, 3]}}}})
    with pytest.raises(ValueError, match="motion_errors"):
        write_spec(t, tmp_path / "spec.json")
    spec = write_spec(truth({}), tmp_path / "spec.json")  # and without them it works
    assert yaml.safe_load((tmp_path / "spec.json").read_text())["links"] == spec["links"]
