"""The gap diagnosis names a withheld exponential warm-up (identification/gap/warmup.py):
8 µm·(1 − e^(−t/900 s)) along Z → ``thermal_drift:Z``, exponential, with amplitude and τ."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.rigs.gap_helpers import STYLUS_R, annex_b_setup, gap_truth
from identification.effects import make_effect
from identification.gap import diagnose
from identification.gap.simlog import simulate
from identification.gap.warmup import TAU_BOUNDS_H, model_of, tau_param, warmup_effect


@pytest.fixture(scope="module")
def warm():
    machine, artefact, poses = annex_b_setup()
    eff = make_effect("thermal_drift", "Z", machine, model="exponential")
    truth = gap_truth(artefact, seed=1, effects=[(eff, np.array([8.0, 900.0 / 3600.0]))])
    data = simulate(machine, artefact, poses, truth, STYLUS_R, 0.5, seed=1)
    return machine, diagnose(machine, artefact, data, STYLUS_R)


def test_a_withheld_warm_up_is_named_with_its_parameters(warm):
    _, rep = warm
    v = rep["verdict"]
    assert (v["effect"], v["axis"]) == ("thermal_drift", "Z"), v["message"]
    sel = v["selected"][0]
    assert sel["model"] == "exponential" and len(v["selected"]) == 1
    amp, tau = sel["params"]["drift_Z_amplitude"], sel["params"]["drift_Z_tau"]
    assert abs(amp["value"] - 8.0) < 3 * amp["std"] + 0.5 and amp["unit"] == "um"
    assert tau["unit"] == "h" and TAU_BOUNDS_H[0] < tau["value"] < TAU_BOUNDS_H[1]
    assert abs(tau["value"] - 0.25) < 3 * tau["std"]
    # the held-out gap shrinks to the floor (the issue: ≤ 1.5 × floor) and the warm-up also
    # predicts stretches of the run it did not see
    assert v["holdout_rms_after_um"] <= 1.5 * rep["noise_floor_um"] < v["holdout_rms_before_um"]
    assert rep["time_check"]["confirmed"]
    # the straight line is a candidate too, and explains less
    lin = [c for c in rep["candidates"] if c["effect"] == "thermal_drift" and c["axis"] == "Z"
           and c["model"] == "linear"]
    assert lin and lin[0]["holdout_rms_um"] > v["holdout_rms_after_um"]


def test_warm_up_effects_of_different_tau_are_different_candidates():
    machine, _, _ = annex_b_setup()
    a, b = warmup_effect(machine, "Z", 0.25), warmup_effect(machine, "Z", 0.5)
    assert a != b and a.label == b.label == "thermal_drift:Z"
    assert tau_param(a) == {} and model_of(a) == {"model": "linear"}  # not profiled
    assert model_of(make_effect("straightness", "X", machine)) == {}
