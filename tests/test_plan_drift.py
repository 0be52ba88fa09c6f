"""``rumba plan`` on a warming machine (issue 22, programs/plan_drift.py): what the plans' timing
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
    lines = [x for x in out.getvalue().splitlines() if "over the run" in x]
    # both plans, linear and warm-up each, separable, with a u per axis and the link cost
    assert len(lines) == 4, out.getvalue()
    assert all("separable from the links, u X/Y/Z" in x and "grows at most ×" in x
               for x in lines)
    assert any(x.startswith("shift-start-14poses: warm-up (τ 15 min)") for x in lines)


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
