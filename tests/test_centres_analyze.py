"""`rumba analyze --centres`: the same estimate as the touches gave, instrument frames estimated
with the setup, per-centre uncertainties, and seed 001's published Table 1 (one indexation)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from contracts.centres_file import read_centres, write_centres
from contracts.probing_log import write_log
from contracts.setup_files import load_artefact, load_machine, load_plan
from daemon.analysis.touch_centres import rows_to_centres
from daemon.cli.main import main
from identification.estimate import estimate
from identification.frame import estimate_weighted
from programs.dialects import get_dialect
from programs.toolpath import build_program
from simulators.errors_schema import errors_from_dict
from simulators.exact_log import THESIS_LINKS_UM_URAD
from simulators.offline import run_sync
from simulators.truth import TruthModel
from tests.regen_centres_fixtures import DMIS_ROTATION_DEG, DMIS_TRANSLATION_MM, rotation

ROOT = Path(__file__).resolve().parents[1]
CFG = ROOT / "config"
DATA = ROOT / "tests" / "data" / "centres"
MACHINE = str(CFG / "machines/thesis_wcbxfzyt.yaml")
ARTEFACT = str(CFG / "artefacts/thesis_4ball.yaml")
PLAN = str(CFG / "plans/thesis_annexB_14poses.yaml")
FRAME_LINKS = {"EA0B", "EC0B", "EB0C"}  # thesis machine: absorbed by an instrument's rotation


def _analyze(tmp_path: Path, name: str, *args: str) -> dict:
    out = tmp_path / f"{name}.json"
    assert main(["analyze", *args, "--machine", MACHINE, "--artefact", ARTEFACT,
                 "--json", str(out)]) == 0
    return json.loads(out.read_text(encoding="utf-8"))


@pytest.fixture(scope="module")
def sim_log(tmp_path_factory) -> Path:
    """A run of the annex-B plan on the offline simulator (Table B.2 links, probe noise)."""
    m, mf = load_machine(MACHINE)
    a = load_artefact(ARTEFACT)
    errors = errors_from_dict(yaml.safe_load((CFG / "errors/thesis_tableB2.yaml").read_text()))
    res = run_sync(TruthModel.build(m, mf, a, errors),
                   get_dialect("fanuc").render(build_program(m, mf, a, load_plan(PLAN))),
                   "fanuc", seed=12)
    assert res.state == "done", res.alarm
    path = tmp_path_factory.mktemp("sim") / "run.csv"
    write_log(path, res.rows)
    return path


def test_centres_of_a_simulated_run_give_the_touches_estimate(sim_log: Path, tmp_path: Path):
    centres = tmp_path / "centres.csv"
    by_log = _analyze(tmp_path, "log", "--log", str(sim_log), "--validate-poses",
                      "3,4,5,7,9,10,11", "--write-centres", str(centres))
    cf = read_centres(centres)
    assert len(cf.rows) == 56 and cf.frame == "machine" and not cf.u_stated
    by_centres = _analyze(tmp_path, "centres", "--centres", str(centres), "--validate-poses",
                          "3,4,5,7,9,10,11")
    assert set(by_centres["links"]) == set(by_log["links"])
    for k, v in by_log["links"].items():
        assert by_centres["links"][k]["value"] == pytest.approx(v["value"], abs=1e-9)
        assert by_centres["links"][k]["std"] == pytest.approx(v["std"], abs=1e-9)
    assert by_centres["validation"] == by_log["validation"]
    assert by_centres["health"] == [] and "touch probe" in by_centres["measured_by"]


def test_weighted_estimator_is_the_estimator_in_machine_axes():
    m, _ = load_machine(MACHINE)
    a = load_artefact(ARTEFACT)
    from contracts.probing_log import read_log

    data = rows_to_centres(read_log(CFG / "examples/thesis_annexB_14poses.csv", a), a, 3.0)
    for sigma in (None, [0.66, 0.98, 0.44]):
        # the weighted estimator (per-centre σ, instrument frame) holds no per-visit scatter:
        # it is the touch path's estimate with independent centres (that one's
        # covariance is now always the visit sandwich, not only past the index test)
        ref = estimate(m, a, data.centres, sigma_um=sigma, visit_scatter=False)
        got, frame = estimate_weighted(m, a, data.centres, sigma_um=sigma)
        assert frame is None and got.layout == ref.layout
        np.testing.assert_allclose(got.p, ref.p, rtol=0, atol=1e-12)
        np.testing.assert_allclose(got.std, ref.std, rtol=1e-9)
        assert got.unobservable == ref.unobservable and got.sigma_dof == ref.sigma_dof


def vars_of(row) -> list:
    return [getattr(row, f) for f in row.__slots__]


def test_uncertainty_per_centre_weights_the_estimate(sim_log: Path, tmp_path: Path):
    centres = tmp_path / "c.csv"
    main(["analyze", "--log", str(sim_log), "--machine", MACHINE, "--artefact", ARTEFACT,
          "--write-centres", str(centres)])
    rows = read_centres(centres).rows
    uniform = tmp_path / "u.csv"
    write_centres(uniform, [r.__class__(*[*vars_of(r)[:-1], 0.7]) for r in rows])
    given = _analyze(tmp_path, "given", "--centres", str(centres), "--repeatability-um", "0.7")
    per_centre = _analyze(tmp_path, "u", "--centres", str(uniform))
    assert per_centre["estimation"]["sigma_from"] == "given (u_um column)"
    for k, v in given["links"].items():  # equal weights: the same estimate by either path
        assert per_centre["links"][k]["value"] == pytest.approx(v["value"], abs=1e-6)
        # the stated σ per axis goes through the touch path's estimate, whose covariance adds
        # the index scatter estimated on top of the stated centre σ (visit sandwich); the
        # per-centre path's is the independent one: never larger
        assert per_centre["links"][k]["std"] <= v["std"] * (1 + 1e-3)
    # one ball's centres 20× less certain: its weight falls, the estimate moves, stds grow
    heavy = tmp_path / "h.csv"
    write_centres(heavy, [r.__class__(*[*vars_of(r)[:-1], 14.0 if r.ball == "B3" else 0.7])
                          for r in rows])
    weighted = _analyze(tmp_path, "h", "--centres", str(heavy))
    assert weighted["setup"]["balls"]["B3"]["std"][0] > 5 * per_centre["setup"]["balls"]["B3"][
        "std"][0]


def test_cmm_frame_is_estimated_and_its_links_are_named(tmp_path: Path):
    r = _analyze(tmp_path, "dmis", "--centres", str(DATA / "dmis_cmm.dmo"), "--plan", PLAN)
    fr = r["instrument_frame"]
    assert fr is not None and "frame instrument" in r["measured_by"]
    # the frame's rotation also takes up the absorbed links (EC0B −23, EB0C 26 µrad): ~35 µrad
    diff = np.array(fr["rotation"]) @ rotation(DMIS_ROTATION_DEG).T - np.eye(3)
    assert 20e-6 < np.abs(diff).max() < 60e-6
    np.testing.assert_allclose(fr["translation_mm"], DMIS_TRANSLATION_MM, atol=1.0)
    assert {k for k, v in fr["std"].items() if v is None} == {"frame tx", "frame ty",
                                                              "frame tz"}
    assert all(0 < fr["std"][f"frame r{a}"] < 5 for a in "xyz")  # µrad
    assert set(r["unobservable"]) >= FRAME_LINKS and not FRAME_LINKS & set(r["links"])
    for k in FRAME_LINKS:
        assert "frame r" in r["unobservable_absorbed_by"][k]
    assert set(r["links"]) == {"EX0C", "EA0C", "EB0Z", "EA0Y", "EC0Y"}
    for k, v in r["links"].items():  # the injected Table B.2 values, within 3 u
        assert abs(v["value"] - THESIS_LINKS_UM_URAD[k]) < 3 * v["std"], (k, v)
    assert r["residual_rms_um"] < 1.0 and len(r["volumetric"]) == 56


def test_kinopt_program_of_one_ball(tmp_path: Path):
    r = _analyze(tmp_path, "k", "--centres", str(DATA / "kinopt_B1.nc"), "--ball", "B1")
    assert set(r["setup"]["balls"]) == {"B1"} and r["estimation"]["centres"] == 14
    assert any("balls ['B2', 'B3', 'B4']" in w for w in r["warnings"])
    for k, v in r["links"].items():
        assert abs(v["value"] - THESIS_LINKS_UM_URAD[k]) < 3 * v["std"], (k, v)


def test_seed001_table1_goes_through_and_says_what_one_indexation_gives(tmp_path: Path,
                                                                       capsys):
    out = tmp_path / "s.json"
    assert main(["analyze", "--centres", str(CFG / "examples/seed001_table1_centres.csv"),
                 "--machine", str(CFG / "machines/seed001_wbzfxyct.yaml"), "--artefact",
                 str(CFG / "artefacts/seed001_5ball.yaml"), "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "ONE indexation" in text and "none identifiable" in text
    r = json.loads(out.read_text(encoding="utf-8"))
    assert r["indexations"] == 1 and r["links"] == {} and r["identifiable"] == []
    assert r["centres"] == 5 and len(r["distances"]) == 10
    # Table 1 is the artefact file's own calibration: its shape agrees to the last digit
    assert max(abs(d["deviation_um"]) for d in r["distances"]) < 1e-3
    assert r["rigid_fit"]["residual_max_um"] < 1e-3
    assert r["repeat_scatter_um"] is None
    assert any("no noise floor" in s for s in r["statements"])
    assert any("instrument frame" in s for s in r["statements"])


def test_centres_errors_are_one_line(tmp_path: Path, capsys):
    bad = tmp_path / "bad.csv"
    bad.write_text("# rumba-centres v1\nrun_id,seq\n", encoding="utf-8")
    assert main(["analyze", "--centres", str(bad), "--machine", MACHINE, "--artefact",
                 ARTEFACT]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "bad.csv: line 2: expected the header" in err
    assert err.count("\n") == 1
    assert main(["analyze", "--centres", str(DATA / "dmis_cmm.dmo"), "--machine", MACHINE,
                 "--artefact", ARTEFACT]) == 2
    assert "--plan" in capsys.readouterr().err
    assert main(["analyze", "--centres", str(bad), "--fixed-radius", "--machine", MACHINE,
                 "--artefact", ARTEFACT]) == 2
