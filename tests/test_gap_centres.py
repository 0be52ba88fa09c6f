"""`rumba gap` without touches (`--centres`) and with exact touches: the noise floor comes from
stated uncertainties or repeats, never from a zero form residual."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from benchmarks.rigs import gap_helpers
from benchmarks.rigs.gap_helpers import STYLUS_R, annex_b_setup, gap_truth, log_rows
from contracts.centres_file import read_centres, write_centres
from contracts.probing_log import write_log
from daemon.cli.main import main
from identification.effects import make_effect
from identification.gap import Options, diagnose
from identification.gap.simlog import simulate

MACHINE = str(gap_helpers.MACHINE)
ARTEFACT = str(gap_helpers.ARTEFACT)
# 0.5 µm trigger scatter along the approach → centre std of a 4 diagonal + pole fit (synth.py)
CENTRE_STD_UM = "0.354,0.354,0.559"


@pytest.fixture(scope="module")
def setup():
    return annex_b_setup()


def _centres(tmp_path: Path, data, artefact, name: str = "c") -> Path:
    log, out = tmp_path / f"{name}.log.csv", tmp_path / f"{name}.csv"
    write_log(log, log_rows(data, artefact))
    assert main(["analyze", "--log", str(log), "--machine", MACHINE, "--artefact", ARTEFACT,
                 "--stylus-diameter", str(2 * STYLUS_R), "--write-centres", str(out)]) == 0
    return out


def test_exact_touches_take_the_floor_from_a_stated_repeatability(setup):
    machine, artefact, poses = setup
    eff = make_effect("gravity_sag", None, machine)
    truth = gap_truth(artefact, effects=[(eff, np.array([3.0]))])
    data = simulate(machine, artefact, poses, truth, STYLUS_R, 0.0, seed=1)
    # before: a floor of 0.001 µm from the zero form residual, any gap "× 1e10 the floor"
    with pytest.raises(ValueError, match=r"touches are exact.*--repeatability-um"):
        diagnose(machine, artefact, data, STYLUS_R)
    rep = diagnose(machine, artefact, data, STYLUS_R,
                   options=Options(repeatability_um=(0.5, 0.5, 0.5)))
    assert rep["noise_floor_um"] == pytest.approx(0.5)
    assert rep["noise"]["source"].startswith("touches exact")
    assert "stated repeatability 0.5/0.5/0.5" in rep["noise"]["source"]
    assert rep["verdict"]["effect"] == "gravity_sag"
    assert 3.0 < rep["baseline"]["gap_ratio"] < 1e3
    assert not any(c["by"] == "direction" for c in rep["breakdowns"])  # no form residual


def test_gap_on_centres_names_the_effect_and_what_centres_cannot_see(setup, tmp_path, capsys):
    machine, artefact, poses = setup
    eff = make_effect("gravity_sag", None, machine)
    data = simulate(machine, artefact, poses,
                    gap_truth(artefact, effects=[(eff, np.array([3.0]))]),
                    STYLUS_R, 0.5, seed=4)
    centres = _centres(tmp_path, data, artefact)
    out = tmp_path / "gap.json"
    assert main(["gap", "--centres", str(centres), "--machine", MACHINE, "--artefact",
                 ARTEFACT, "--repeatability-um", CENTRE_STD_UM, "--json", str(out)]) == 0
    rep = json.loads(out.read_text(encoding="utf-8"))
    assert rep["verdict"]["effect"] == "gravity_sag"
    assert rep["noise"]["source"].startswith("centres: stated uncertainty (--repeatability-um)")
    stated = np.sqrt((0.354**2 * 2 + 0.559**2) / 3)
    assert rep["noise"]["sigma_touch_um"] == pytest.approx(stated, abs=1e-3)
    # the floor adds the per-visit components' REML estimates, significant or not (an
    # unbiased variance, not one truncated at its test): never below the stated noise, and
    # here (none detected, 14 visits) within a few per cent of it
    assert stated - 1e-3 <= rep["noise_floor_um"] <= 1.1 * stated
    # a touch probe's direction pattern is a constant shift on centres: the setup takes it
    assert "probe_pretravel" in {i["effect"] for i in rep["invisible"]}
    assert not any(c["by"] == "direction" for c in rep["breakdowns"])
    assert "centres: stated uncertainty" in capsys.readouterr().out


def test_gap_on_centres_with_repeats_and_without(setup, tmp_path, capsys):
    machine, artefact, poses = setup
    truth = gap_truth(artefact)
    runs = [simulate(machine, artefact, poses, truth, STYLUS_R, 0.5, seed=40 + k)
            for k in range(2)]
    one = _centres(tmp_path, runs[0], artefact, "one")
    # no stated uncertainty and no repeat: no floor, one line
    assert main(["gap", "--centres", str(one), "--machine", MACHINE, "--artefact",
                 ARTEFACT]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no noise floor" in err and "--repeatability-um" in err
    # the same run measured twice (repeat 1 a second pass): the floor is their scatter
    second = read_centres(_centres(tmp_path, runs[1], artefact, "two")).rows
    rows = read_centres(one).rows + [replace(r, seq=r.seq + 1000, t_s=r.t_s + 3600.0, repeat=1)
                                     for r in second]
    both = tmp_path / "both.csv"
    write_centres(both, rows)
    out = tmp_path / "rep.json"
    assert main(["gap", "--centres", str(both), "--machine", MACHINE, "--artefact", ARTEFACT,
                 "--split", "pose", "--json", str(out)]) == 0
    rep = json.loads(out.read_text(encoding="utf-8"))
    assert rep["noise"]["source"].startswith("centres: scatter between repeats")
    assert 0.2 < rep["noise_floor_um"] < 0.8 and rep["verdict"]["effect"] == "none"
    # an instrument frame is analyze's business: the gap twin works in machine axes
    cmm = tmp_path / "cmm.csv"
    write_centres(cmm, rows, frame="instrument")
    assert main(["gap", "--centres", str(cmm), "--machine", MACHINE, "--artefact",
                 ARTEFACT]) == 2
    assert "instrument frame" in capsys.readouterr().err
