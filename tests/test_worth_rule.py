"""The worth rule (identification/worth.py): a change is proposed only when it is observable,
over its own expanded uncertainty and moves a probed centre by at least guards.min_effect_um;
the changes together only when they gain that much on the max link-caused distortion and make
nothing worse; a refusal or a reason words its two figures so that they differ, never
"-0.00". On the demo machine's geometry (thesis machine, Siemens section, 14-pose plan)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import yaml

from contracts.probing_log import write_log
from contracts.setup_files import load_artefact, load_controller_kinematics, load_plan
from daemon.compensation.propose import propose
from daemon.config import load_daemon_config
from daemon.reports.proposal import proposal_dict
from daemon.store.journal import Store
from identification.compensation import (
    CompensationPlan,
    Guards,
    ParamChange,
    check_guards,
    plan_compensation,
)
from identification.estimate import estimate
from identification.worth import pair, plain
from simulators.exact_log import Truth, shipped_run_rows, to_internal
from tests.cli_helpers import run_cli
from tests.test_compensate import CONFIG, LINKS, MACHINE, PLAN, _world
from tests.test_compensation_math import _centres

CFG = CONFIG


@pytest.fixture(scope="module")
def demo_plan() -> CompensationPlan:
    """The plan of the demo machine's first check (EX0C −38 µm and Table B.2's tilts)."""
    machine, spec = load_controller_kinematics(CFG / "machines/thesis_wcbxfzyt.yaml")
    a = load_artefact(CFG / "artefacts/thesis_4ball.yaml")
    poses = [(p.b_deg, p.c_deg) for p in load_plan(CFG / "plans/shift_start_14poses.yaml").poses]
    err = yaml.safe_load((CFG / "errors/demo_hmc.yaml").read_text())
    truth = Truth(to_internal(err["links"]),
                  np.array(list(err["setup"]["balls_um"].values()), float) * 1e-3,
                  np.array(err["setup"]["probe_um"], float) * 1e-3)
    c = _centres(machine, a, poses, truth)
    est = estimate(machine, a, c)
    return plan_compensation(machine, a, est, spec.to_math(), c.b_deg, c.c_deg)


def _scaled(plan: CompensationPlan, name: str, delta: float, u: float) -> CompensationPlan:
    """``plan`` with only ``name`` changed, by ``delta`` (its displacement scaled to it)."""
    ch = next(c for c in plan.changes if c.name == name)
    changes = [dataclasses.replace(c, delta=delta, u_expanded=u) if c.name == name else
               dataclasses.replace(c, delta=0.0, u_expanded=1.0) for c in plan.changes]
    return dataclasses.replace(plan, changes=changes,
                               change_disp_mm={name: plan.change_disp_mm[name] * (delta
                                                                                 / ch.delta)})


def test_the_demo_plan_proposes_what_matters(demo_plan):
    r = check_guards(demo_plan, Guards())
    accepted = {c.name for c in r.accepted}
    assert "c-x" in accepted  # EX0C −38 µm: 23 µm at the probed centres
    for c in r.accepted:
        assert abs(c.delta) > c.u_expanded and demo_plan.effect_um(c.name) >= 2.0, c
    # predicted after: of what is proposed, below before by at least the threshold
    before, after = demo_plan.distortion_before_um, r.after_um
    assert after[1] <= before[1] - 2.0 and after[0] <= before[0]


def test_a_significant_tilt_too_small_to_matter_is_not_proposed(demo_plan):
    """After a PASS verification the panel proposed $TC_CARR7[1] (b-tilt-c) Δ −5.23 µrad,
    U 4.95 µrad, Confirm enabled: significant, but its effect at the probed centres is under
    a micrometre — no verification run could see it."""
    plan = _scaled(demo_plan, "b-tilt-c", -5.23e-6, 4.95e-6)
    effect = plan.effect_um("b-tilt-c")
    assert 0.1 < effect < 2.0, effect
    r = check_guards(plan, Guards())
    assert r.accepted == [] and r.refused == [], r
    why = dict((c.name, w) for c, w in r.skipped)["b-tilt-c"]
    e, f = pair(effect, 2.0)
    assert why == (f"moves the probed ball centres by {e} µm at most, under the {f} µm a "
                   "change must move them to be worth writing (guards.min_effect_um)")
    # a threshold of 0 (the machine file may say so) proposes it
    assert [c.name for c in check_guards(plan, Guards(min_effect_mm=0.0)).accepted] == [
        "b-tilt-c"]


def test_changes_that_gain_too_little_together_are_not_proposed():
    """Two changes each worth it alone, whose effects mostly cancel: the max link-caused
    distortion would fall by 0.3 µm only — nothing proposed, the reason with both figures."""
    link = np.array([[0.003, 0.0, 0.0], [0.0, 0.001, 0.0]])
    disp = {"a": np.array([[0.0025, 0.0, 0.0], [0.0, 0.0, 0.0]]),
            "b": np.array([[-0.0022, 0.0, 0.0], [0.0, 0.0, 0.0]])}
    plan = CompensationPlan([ParamChange("a", "pivot", 0.0025, 0.0001, True),
                             ParamChange("b", "pivot", -0.0022, 0.0001, True)], {}, {}, {},
                            (2.236, 3.0), (0.2, 0.3), (2.04, 2.7), link, disp)
    r = check_guards(plan, Guards())
    assert r.accepted == [] and r.refused == []
    assert r.not_worth == ("together they would lower the link-caused distortion max by 0.30 "
                           "µm only (3.0 → 2.7 µm), under the 2.00 µm a compensation must "
                           "gain to be worth writing (guards.min_effect_um)")
    assert r.after_um == plan.distortion_before_um  # nothing written: nothing predicted


@pytest.mark.parametrize("after_max, refused", [
    (4.7043, []),  # a rounding above before: no gain, not "worse"
    (4.73, ["predicted after compensation max 4.73 µm exceeds the link-caused distortion max "
            "4.70 µm before it: the changes would make the machine worse"]),
])
def test_worse_is_worded_with_figures_that_differ(after_max, refused):
    """"predicted after compensation max 4.7 µm exceeds the link-caused distortion max 4.7 µm
    before it" said nothing: the figures are worded with the decimals that tell them apart,
    and a rise of a rounding is no gain, not a machine made worse."""
    ok = ParamChange("EA0C", "orientation", -15e-6, 4e-6, True)
    plan = CompensationPlan([ok], {}, {}, {}, (2.6, 4.7012), (1.0, 1.0), (2.6, after_max))
    r = check_guards(plan, Guards())
    assert r.refused == refused and r.accepted == []
    if not refused:
        assert r.not_worth.startswith("together they would not lower the link-caused "
                                      "distortion max (4.701 → 4.704 µm), under the 2.0 µm")


def test_numbers_never_read_minus_zero_and_pairs_differ():
    assert plain(-0.001, 2) == "0.00" and plain(-0.001, 2, sign=True) == "0.00"
    assert plain(-0.006, 2, sign=True) == "-0.01" and plain(0.5, 1, sign=True) == "+0.5"
    assert pair(4.71, 4.74) == ("4.71", "4.74") and pair(5.0, 4.0) == ("5.0", "4.0")
    assert pair(1.0, 1.0) == ("1.0000", "1.0000")  # equal: as precise as it gets


def test_a_pass_verification_proposes_nothing_and_says_why(tmp_path, capsys):
    """After a PASS verification the panel proposed a further change with Confirm enabled:
    the verification run of a compensation that PASSes proposes nothing (the worth rule's
    rule 5), here saying that x-offset did not hold (a person looks before a second write)."""
    cfg = _world(tmp_path, capsys)
    assert run_cli(["compensate", "--config", cfg, "--confirm", "synth", "--by", "alice"],
                   capsys)[0] == 0
    log = tmp_path / "verify.csv"  # the C line moved 20 µm more: EX0C −20 µm after it
    write_log(log, shipped_run_rows(MACHINE, CONFIG / "artefacts/thesis_4ball.yaml", PLAN,
                                    {**LINKS, "EX0C": -60}, run_id="verify"))
    assert run_cli(["history", "--config", cfg, "--import", str(log), "--machine", "lcnc"],
                   capsys)[0] == 0
    conf = load_daemon_config(cfg)
    store = Store(conf.store_path)
    try:
        assert store.run("verify").verdict == "PASS"
        p = propose(conf.machines["lcnc"], store, "verify")
        d = proposal_dict(p)
    finally:
        store.close()
    x = next(c for c in p.plan.changes if c.name == "x-offset")
    assert abs(x.delta) > x.u_expanded and p.plan.effect_um("x-offset") > 2.0  # worth alone
    assert p.values == [] and p.program is None and not d["applicable"]
    assert d["state"] == "nothing" and d["writes"] == []
    assert d["why"].startswith("nothing worth writing: run verify verifies compensation #1 "
                               "(from run synth) and PASSed; x-offset would move again beyond "
                               "U (the compensation did not hold"), d["why"]
    code, out, _ = run_cli(["compensate", "--config", cfg, "verify"], capsys)
    assert code == 0 and d["why"] in out and "-0.00" not in out, out
    assert not (tmp_path / "reports" / "proposal-lcnc-verify.json").exists()
