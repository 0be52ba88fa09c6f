"""A stated rotary repeatability (machine file ``rotary_repeatability_urad``) as the Type B input
of the daily estimate's index components (identification/estimate_scatter.py):
used where a run's 8 visits cannot pin σ, overridden with a warning where the run shows it
significantly worse, nothing changed without one; and it reaches the analysis from the file."""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from contracts.probing_log import write_log
from contracts.setup_files import load_artefact, load_machine, load_plan
from daemon.analysis.result import Analysis
from daemon.cli.main import main
from identification.drift import estimate_drift_aware, shape_values
from identification.estimate import estimate
from identification.model import Centres
from simulators.exact_log import make_rows, true_centres
from tests.drift_helpers import SIGMA, shift_visits, thesis_truth

ROOT = Path(__file__).resolve().parents[1]
CFG = ROOT / "config"
FOUR = {"B": 4.0, "C": 4.0}
# The links' u carry the REML variance components, found to the optimum (Newton with the exact
# Hessian, identification/visit_reml): between BLAS kernels and thread counts they agree to 3e-10
# relative (1e-8 with the drift's τ), measured on Prescott, Sandybridge, Haswell and AVX-512
# kernels; 1e-6 keeps a margin of 100 and is far below what a stated value moves (×1.05-2.4).
U_RTOL = 1e-6


@pytest.fixture(scope="module")
def sv():
    return shift_visits()


def _centres(sv, seed: int, index_urad: float, warmup_um: float = 0.0) -> Centres:
    """The shift plan's 8 estimate visits, each indexed with its own B/C error of
    ``index_urad`` 1σ (every ball of the visit moves with it), thesis centre noise, and a
    15-min warm-up along Z of ``warmup_um`` over the run."""
    rng = np.random.default_rng(seed)
    d = np.rad2deg(rng.normal(size=(len(sv.visits), 2)) * index_urad * 1e-6)
    xyz = true_centres(sv.machine, sv.artefact,
                       [(b + db, c + dc) for (b, c), (db, dc) in zip(sv.visits, d, strict=True)],
                       thesis_truth()).reshape(-1, 3)
    xyz[:, 2] += warmup_um * 1e-3 * shape_values("exponential", sv.t_s, 900.0)
    bc = np.repeat(np.array(sv.visits), len(sv.artefact.balls), axis=0)
    return Centres(sv.pose, sv.ball, bc[:, 0], bc[:, 1],
                   xyz + rng.normal(size=xyz.shape) * SIGMA * 1e-3, sv.t_s)


def test_a_stated_repeatability_carries_the_index_scatter_a_run_does_not_show(sv):
    """4 µrad true B/C scatter; this run's REML puts σ̂_B at 0 (8 visits cannot pin it). With
    the stated 4 µrad the links widen, most EB0C (× 2.4); the free estimate is still
    reported beside the stated one; stating exactly what REML found changes nothing."""
    m, a = sv.machine, sv.artefact
    c = _centres(sv, 10, 4.0)
    free = estimate(m, a, c)
    assert free.visit_scatter["index B"][0] < 0.5, free.visit_scatter  # the premise
    said = estimate(m, a, c, rotary_repeatability_urad=FOUR)
    ratio = said.std / free.std
    n = len(free.layout.links)
    assert ratio[:n].max() > 1.8, dict(zip(free.layout.links, ratio.round(2), strict=False))
    assert ratio[free.layout.links.index("EB0C")] > 1.8
    assert ratio[:n].min() > 0.99  # both stated above the run's estimates: nothing narrows
    for k in ("index B", "index C"):  # the data's say, reported (σ̂ 0: its u is NaN)
        np.testing.assert_allclose(said.visit_scatter[k], free.visit_scatter[k], rtol=1e-12,
                                   equal_nan=True)
        assert said.visit_scatter[f"{k} stated"][0] == 4.0
        assert said.visit_scatter[f"{k} stated"][2] == 1.0  # σ̂ below stated: nothing against it
    assert not [w for w in said.warnings if "machine file states" in w]
    same = {ax: free.visit_scatter[f"index {ax}"][0] for ax in "BC"}
    again = estimate(m, a, c, rotary_repeatability_urad=same)
    assert np.allclose(again.std, free.std, rtol=2e-3), again.std / free.std


def test_a_stated_value_far_below_a_real_10_urad_scatter_is_overridden_with_a_warning(sv):
    """10 µrad true scatter, the file states 1: both axes' tests reject it, the links are
    those of the free estimate (the same numbers), and one warning per axis names it."""
    m, a = sv.machine, sv.artefact
    c = _centres(sv, 2, 10.0)
    free = estimate(m, a, c)
    said = estimate(m, a, c, rotary_repeatability_urad={"B": 1.0, "C": 1.0})
    np.testing.assert_array_equal(said.std, free.std)
    for ax in "BC":
        sig = free.visit_scatter[f"index {ax}"][0]
        assert sig > 5.0
        assert said.visit_scatter[f"index {ax} stated"][2] < 0.01
        hits = [w for w in said.warnings if re.match(
            rf"{ax} indexing repeatability {sig:.1f} µrad estimated, machine file states 1 ", w)]
        assert len(hits) == 1, said.warnings
    # an axis stated right keeps its stated value: only C is overridden
    one = estimate(m, a, c, rotary_repeatability_urad={"B": 10.0, "C": 1.0})
    assert [w[0] for w in one.warnings if "machine file states" in w] == ["C"]
    assert not np.array_equal(one.std, free.std)


def test_the_drift_aware_estimate_gives_the_verdict_once(sv):
    """A warming run: the drift refit's sandwich takes the stated value too and its own
    test's warning replaces the plain fit's (one per axis, not two)."""
    m, a = sv.machine, sv.artefact
    c = _centres(sv, 2, 10.0, warmup_um=10.0)
    out = estimate_drift_aware(m, a, c, rotary_repeatability_urad={"B": 1.0, "C": 1.0})
    assert out.status == "selected", out.message
    warns = [w for w in out.estimate.warnings if "machine file states" in w]
    assert sorted(w[0] for w in warns) == ["B", "C"], warns
    c = _centres(sv, 10, 4.0, warmup_um=10.0)
    free = estimate_drift_aware(m, a, c)
    said = estimate_drift_aware(m, a, c, rotary_repeatability_urad=FOUR)
    assert said.status == free.status == "selected"
    assert said.estimate.visit_scatter["index B stated"][0] == 4.0
    assert (said.estimate.std / free.estimate.std).max() > 1.5


def test_without_a_stated_value_the_estimate_is_the_one_before(sv):
    """The u of these two runs without a stated value, as the estimate gives them with nothing
    stated: nothing moves, and no stated entry shows; the drift-aware run's too (the drift
    fitted on every separable axis, the choice's share over the shapes). The plain run's are
    those of the REML optimum, σ̂_B 0.155 µrad: the optimiser in σ before stopped at σ_B = 0,
    where −2ℓ still fell along σ_B² (∂/∂σ_B² = −0.025; 3e-4 lower at the optimum), and gave
    these u up to 0.25 % apart (EB0C 0.8237 then)."""
    m, a = sv.machine, sv.artefact
    before = [3.5934693, 2.3097185, 0.1773432, 2.6338671, 0.8256806, 2.2799924, 3.5777120,
              2.5260037]
    c = _centres(sv, 10, 4.0)
    for kw in ({}, {"rotary_repeatability_urad": None}, {"rotary_repeatability_urad": {}}):
        e = estimate(m, a, c, **kw)
        np.testing.assert_allclose([u for _, u, _ in e.links_si().values()], before,
                                   rtol=U_RTOL)
        assert not [k for k in e.visit_scatter if "stated" in k]
    drift_before = [3.3367176, 2.7319385, 0.2183315, 2.4784543, 0.7961622, 2.3566043, 3.5193551,
                    2.8253890]
    d = estimate_drift_aware(m, a, _centres(sv, 10, 4.0, warmup_um=10.0))
    np.testing.assert_allclose([u for _, u, _ in d.estimate.links_si().values()], drift_before,
                               rtol=U_RTOL)


@pytest.fixture(scope="module")
def scatter_log(tmp_path_factory) -> Path:
    """A probing log of the annex-B 14-pose plan on a machine whose every indexation stops
    10 µrad 1σ off on B and C (the log records the commanded angles, as a controller does)."""
    m, _ = load_machine(CFG / "machines/thesis_wcbxfzyt.yaml")
    a = load_artefact(CFG / "artefacts/thesis_4ball.yaml")
    plan = load_plan(CFG / "plans/thesis_annexB_14poses.yaml")
    poses = [(p.b_deg, p.c_deg) for p in plan.poses]
    d = np.rad2deg(np.random.default_rng(7).normal(size=(len(poses), 2)) * 10e-6)
    off = [(b + db, c + dc) for (b, c), (db, dc) in zip(poses, d, strict=True)]
    rows = make_rows(m, a, off, thesis_truth(), touch_noise_um=0.5, seed=3)
    rows = [dataclasses.replace(r, b_cmd_deg=poses[r.pose][0], c_cmd_deg=poses[r.pose][1],
                                b_deg=poses[r.pose][0], c_deg=poses[r.pose][1]) for r in rows]
    p = tmp_path_factory.mktemp("log") / "run.csv"
    write_log(p, rows)
    return p


def _analyse(log: Path, tmp: Path, stated: dict | None) -> dict:
    """`rumba analyze --json` with the thesis machine file, stating ``stated`` or nothing."""
    data = yaml.safe_load((CFG / "machines/thesis_wcbxfzyt.yaml").read_text())
    if stated is not None:
        data["rotary_repeatability_urad"] = stated
    machine = tmp / f"m{len(list(tmp.iterdir()))}.yaml"
    machine.write_text(yaml.safe_dump(data))
    out = tmp / "r.json"
    assert main(["analyze", "--log", str(log), "--machine", str(machine), "--artefact",
                 str(CFG / "artefacts/thesis_4ball.yaml"), "--json", str(out)]) == 0
    return json.loads(out.read_text())


def test_the_machine_files_value_reaches_rumba_analyze(scatter_log, tmp_path, capsys):
    """Through the CLI (load_machine → analyse_centres → drift-aware estimate): a stated 1 µrad
    under a 10 µrad scatter is named in the JSON's warnings and leaves the links as without
    it; a stated 40 µrad (above what the run shows) widens them; none: no such warning."""
    plain = _analyse(scatter_log, tmp_path, None)
    low = _analyse(scatter_log, tmp_path, {"B": 1, "C": 1})
    high = _analyse(scatter_log, tmp_path, {"B": 40, "C": 40})
    capsys.readouterr()
    assert not [w for w in plain["warnings"] if "machine file states" in w]
    named = [w for w in low["warnings"] if "machine file states 1 " in w]
    assert sorted(w[0] for w in named) == ["B", "C"], low["warnings"]
    assert {k: v["std"] for k, v in low["links"].items()} == \
        {k: v["std"] for k, v in plain["links"].items()}
    ratio = {k: high["links"][k]["std"] / v["std"] for k, v in plain["links"].items()}
    assert max(ratio.values()) > 1.5 and min(ratio.values()) > 0.99, ratio
    assert not [w for w in high["warnings"] if "machine file states" in w]
    # the JSON's estimation block: per axis the run's estimate, the stated value, which is used
    for r, used in ((plain, "estimated"), (low, "estimated"), (high, "stated")):
        ix = {x["axis"]: x for x in r["estimation"]["index_scatter"]}
        assert set(ix) == {"B", "C"} and {x["used"] for x in ix.values()} == {used}
        assert ix["B"]["estimated_urad"] == plain["estimation"]["index_scatter"][0][
            "estimated_urad"] > 5.0
    assert plain["estimation"]["index_scatter"][0]["stated_urad"] is None
    assert [x["stated_urad"] for x in high["estimation"]["index_scatter"]] == [40, 40]
    assert all(x["p_stated"] < 0.01 for x in low["estimation"]["index_scatter"])
    again = Analysis.from_json(low).to_json()
    assert again["estimation"] == low["estimation"]


def test_the_daemons_run_analysis_and_compensation_take_the_machine_files_value():
    """The session's path: MachineSetup.machine_file → pipeline.analyse (the run's analysis)
    and the compensation's own estimate (``identified.identify``): 40 µrad stated on a run
    without index scatter is used (its links widen), nothing stated leaves them as they were."""
    from benchmarks.rigs.daemon_helpers import thesis_rows, thesis_setup
    from daemon.analysis import pipeline
    from daemon.compensation import identified

    plain = thesis_setup(plan="thesis_annexB_14poses")
    mf = plain.machine_file.model_copy(update={"rotary_repeatability_urad": {"B": 40.0,
                                                                               "C": 40.0}})
    said = dataclasses.replace(plain, machine_file=mf)
    hits = [pipeline.row_to_hit(r, plain.machine) for r in thesis_rows(plain, seed=1)]
    a0 = pipeline.analyse(plain, hits, "r0").data
    a1 = pipeline.analyse(said, hits, "r1").data
    assert {x.used for x in a0.estimation.index_scatter} == {"estimated"}
    assert {(x.axis, x.stated_urad, x.used) for x in a1.estimation.index_scatter} == \
        {("B", 40.0, "stated"), ("C", 40.0, "stated")}
    ratio = [a1.links[k].std / v.std for k, v in a0.links.items()]
    assert max(ratio) > 1.5 and min(ratio) > 0.99, ratio
    c = _pipeline_centres(plain, hits)
    e0 = identified.identify(plain, c, "r0", plain.machine)
    e1 = identified.identify(said, c, "r1", plain.machine)
    assert "index B stated" not in e0.visit_scatter and e1.visit_scatter["index B stated"][0] == 40
    assert (e1.std / e0.std).max() > 1.5


def _pipeline_centres(setup, hits) -> Centres:
    """The estimation centres of ``hits`` (their sphere fits, validation poses held out)."""
    from daemon.analysis.pipeline import hit_to_row
    from daemon.analysis.touch_centres import rows_to_centres

    rows = [hit_to_row("r", h, setup.machine) for h in hits if h.triggered]
    c = rows_to_centres(rows, setup.artefact, setup.plan.stylus_radius_mm).centres
    return c.subset(~np.isin(c.pose, list(setup.validate_poses)))
