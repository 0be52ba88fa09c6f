"""``rumba plan`` on a warming machine (programs/plan_drift.py): what the plans' timing
can separate of a TCP drift, its predicted u, and what a plan cannot separate."""

from __future__ import annotations

import io
from contextlib import redirect_stderr, redirect_stdout

import numpy as np

from contracts.setup_files import load_artefact, load_machine, load_plan
from daemon.cli.main import main
from programs.plan_drift import drift_plan, plan_times_s
from programs.plan_report import estimate_visits, plan_links
from tests.test_plan_optimise import ARGS, ARTEFACT, MACHINE, SHIPPED, SIGMA, TARGETS


def test_rumba_plan_states_the_drift_each_plan_separates(tmp_path):
    out, err = io.StringIO(), io.StringIO()
    with redirect_stdout(out), redirect_stderr(err):
        code = main([*ARGS, "--target", str(TARGETS), "-o", str(tmp_path / "p.yaml")])
    assert code == 0, err.getvalue()
    lines = [x for x in out.getvalue().splitlines() if "separable from the links" in x]
    # both plans, linear and warm-up each, separable, with a u per axis and the link cost
    assert len(lines) == 4, out.getvalue()
    assert all("separable from the links, u X/Y/Z" in x and "grows at most ×" in x
               for x in lines)
    assert any(x.startswith("shift-start-14poses: warm-up (τ 15 min)") for x in lines)
    # and what neither plan can tell: τ itself, short of a warm-up of tens of µm over the run
    tau = [x for x in out.getvalue().splitlines() if "known to ±50 % only from" in x]
    assert [x.split(":")[0] for x in tau] == ["shift-start-14poses", "shift-start-optimised"]
    # the summary's link-u growth is the worst of a linear drift and a warm-up
    assert "with a drift estimated too (linear, or a warm-up of τ 10-60 min" in out.getvalue()


def test_a_plan_without_revisit_or_spread_in_time_cannot_separate(tmp_path):
    m, _ = load_machine(MACHINE)
    a = load_artefact(ARTEFACT)
    ref = load_plan(SHIPPED)
    links, _ = plan_links(m, a, ref)
    visits = estimate_visits(ref)
    good = drift_plan(m, a, visits, plan_times_s(ref, 223.0), links, SIGMA)
    assert good.inseparable() == []
    assert all(0.0 < u < 1.0 for u in good.over_run_u_um["exponential"])
    assert 1.0 <= good.link_growth["exponential"] < 3.0
    # visits without time between them (a log without usable times): a drift is one more
    # relocalisation of every pose, never separable
    flat = drift_plan(m, a, visits, np.zeros(len(visits)), links, SIGMA)
    assert set(flat.inseparable()) >= {"linear X", "linear Y", "linear Z"}
    assert flat.lines("p")[0].startswith("p: the plan cannot separate drift from links")


def test_tau_is_what_a_short_plan_cannot_pin_down():
    """A warm-up's τ shows only in the bend of the drift over the run: the shift plan's 3.7 min
    tell a 15-min τ to ±50 % only from tens of µm of drift (Z, the best-measured axis, least)."""
    m, _ = load_machine(MACHINE)
    a = load_artefact(ARTEFACT)
    ref = load_plan(SHIPPED)
    links, _ = plan_links(m, a, ref)
    d = drift_plan(m, a, estimate_visits(ref), plan_times_s(ref, 223.0), links, SIGMA)
    assert all(x >= 0.05 for x in d.tau_separation)  # the bend is separable …
    assert 5.0 < d.tau_from_um[2] < min(d.tau_from_um[:2]) < 200.0  # … but weakly
    short = drift_plan(m, a, estimate_visits(ref), plan_times_s(ref, 60.0), links, SIGMA)
    # a quarter of the time bends a quarter as much: ~4× the drift to see τ (bend ∝ T/τ)
    assert short.tau_from_um[2] > 3 * d.tau_from_um[2]


def test_the_order_search_guards_against_a_warm_up_not_only_a_line():
    """A warm-up with τ estimated bends the drift (t and t² over a short run): it costs the
    links more than a straight line, and the order search takes the worst of both."""
    from programs.design import WARMUP_TAU_H, build_design, drift_u, drift_u_worst

    m, _ = load_machine(MACHINE)
    a = load_artefact(ARTEFACT)
    ref = load_plan(SHIPPED)
    links, _ = plan_links(m, a, ref)
    visits = estimate_visits(ref)
    uniq = sorted(set(visits))
    d = build_design(m, a, uniq, links, SIGMA)
    idx = [uniq.index(v) for v in visits]
    t_h = [x / 3600.0 for x in plan_times_s(ref, 223.0)]
    lin = drift_u(d, idx, t_h)
    warm = [drift_u(d, idx, t_h, tau) for tau in WARMUP_TAU_H]
    assert all(np.all(w >= lin - 1e-12) for w in warm)
    assert max(float(np.max(w / lin)) for w in warm) > 1.02  # the bend costs something
    np.testing.assert_allclose(drift_u_worst(d, idx, t_h), np.max([lin, *warm], axis=0))
