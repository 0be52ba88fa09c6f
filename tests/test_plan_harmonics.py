"""The shipped hold-out plan identifies rotary positioning harmonics on its estimate poses, and
`rumba gap` says when a plan's estimate poses cannot."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.rigs.gap_helpers import ARTEFACT, CONFIG, MACHINE, STYLUS_R, THESIS_LINKS, log_rows
from contracts.probing_log import write_log
from contracts.setup_files import load_artefact, load_machine, load_plan
from daemon.cli.main import main
from identification.effects import make_effect
from identification.gap import diagnose
from identification.gap.simlog import Truth, simulate
from identification.harmonic_support import harmonic_support, warnings
from identification.identifiability import identifiable_links, nominal_centres
from programs.safety import check_program
from programs.toolpath import build_program

NEW = CONFIG / "plans/shift_holdout_14poses.yaml"
OLD = CONFIG / "plans/thesis_annexB_14poses.yaml"


def _roles(path):
    plan = load_plan(path)
    est = [(p.b_deg, p.c_deg) for p in plan.poses if p.role == "estimate"]
    val = [(p.b_deg, p.c_deg) for p in plan.poses if p.role == "validate"]
    return est, val


def _axes(poses):
    return {"B": [b for b, _ in poses], "C": [c for _, c in poses]}


def test_annex_b_roles_leave_the_2nd_harmonic_of_c_to_extrapolation():
    est, val = _roles(OLD)
    msgs = warnings(_axes(est), _axes(val))
    assert msgs == [msgs[0]] and msgs[0].startswith(
        "2nd harmonic of C: the estimate poses give 2C only 3 distinct values; "
        "the validate poses extrapolate it")
    (c2,) = [s for s in harmonic_support(_axes(est), _axes(val)) if not s.ok]
    assert (c2.axis, c2.order, c2.rank) == ("C", 2, 3)
    assert c2.leverage_validate == pytest.approx(7.0) and c2.leverage_estimate == pytest.approx(0.5)
    # one C angle on the estimate poses: not identifiable at all, with or without a hold-out
    assert warnings({"C": [0.0, 180.0]}, orders=(2,)) == [
        "2nd harmonic of C: the estimate poses give 2C only 1 distinct value; they cannot "
        "identify it (rank 1 of 3)"]


def test_shipped_holdout_plan_identifies_orders_1_2_and_every_link():
    new, old = load_plan(NEW), load_plan(OLD)
    est, val = _roles(NEW)
    assert len(est) == len(val) == 7
    # the same indexations as annex B (the same moves), only the roles differ
    assert sorted((p.b_deg, p.c_deg) for p in new.poses) == sorted(
        (p.b_deg, p.c_deg) for p in old.poses)
    assert warnings(_axes(est), _axes(val)) == []
    c2 = next(s for s in harmonic_support(_axes(est), _axes(val)) if (s.axis, s.order) == ("C", 2))
    assert c2.distinct == 6 and c2.leverage_validate <= c2.leverage_estimate + 1e-9
    machine, _ = load_machine(MACHINE)
    artefact = load_artefact(ARTEFACT)
    ident = {p: identifiable_links(machine, artefact, nominal_centres(machine, artefact, e))
             for p, e in (("new", est), ("old", _roles(OLD)[0]))}
    assert ident["new"].links == ident["old"].links and len(ident["new"].links) >= 8
    assert ident["new"].scale_observable == ident["old"].scale_observable


def test_shipped_holdout_plan_passes_the_safety_check():
    machine, mfile = load_machine(MACHINE)
    prog = build_program(machine, mfile, load_artefact(ARTEFACT), load_plan(NEW))
    check_program(prog)  # raises SafetyError naming the move otherwise
    assert len(prog.touches) == 14 * 4 * 5


def _harmonic_truth(artefact, machine, seed: int) -> Truth:
    rng = np.random.default_rng(1000 * seed + 5)
    truth = Truth(dict(THESIS_LINKS), rng.normal(0.0, 0.2, (len(artefact.balls), 3)),
                  rng.normal(0.0, 0.05, 3), index_std_urad={"B": 8.0, "C": 8.0})
    ph = np.random.default_rng(seed).uniform(0, 2 * np.pi)
    eff = make_effect("rotary_positioning", "C", machine)
    truth.effects = [(eff, np.array([0, 0, 0, 40 * np.cos(ph), 40 * np.sin(ph)]))]
    return truth


SEED = 0  # bench_scatter --only harmonic seed 0: annex B roles 1.45 x floor, the new plan 1.08


def _harmonic_ratio(plan) -> tuple[bool, float]:
    """(named rotary_positioning:C, held-out RMS after it ÷ the scatter-aware held-out floor)."""
    machine, _ = load_machine(MACHINE)
    artefact = load_artefact(ARTEFACT)
    truth = _harmonic_truth(artefact, machine, SEED)
    est, val = _roles(plan)
    s = 1000 * SEED + 5
    data = simulate(machine, artefact, est, truth, STYLUS_R, 0.5, seed=s + 7919)
    hold = simulate(machine, artefact, val, truth, STYLUS_R, 0.5, seed=s + 104729)
    rep = diagnose(machine, artefact, data, STYLUS_R, holdout=hold)
    v = rep["verdict"]
    return ((v["effect"], v["axis"]) == ("rotary_positioning", "C"),
            v["holdout_rms_after_um"] / rep["noise"]["holdout_floor_um"])


def test_2nd_harmonic_of_c_under_index_scatter_on_the_holdout_plans():
    # Same machine, same draws: the shipped plan names the harmonic and shrinks the held-out
    # gap to the floor; annex B's roles extrapolate it to their validate poses and keep more
    # of it (seed 0: 1.72 x the floor before the REML fix of the index components, 1.45 after)
    named_new, ratio_new = _harmonic_ratio(NEW)
    named_old, ratio_old = _harmonic_ratio(OLD)
    assert named_new and ratio_new <= 1.5, ratio_new
    assert ratio_old > 1.2 * ratio_new, (named_old, ratio_old, ratio_new)


def test_rumba_gap_warns_when_the_estimate_poses_cannot_identify_a_harmonic(tmp_path, capsys):
    machine, _ = load_machine(MACHINE)
    artefact = load_artefact(ARTEFACT)
    truth = Truth(dict(THESIS_LINKS), np.zeros((len(artefact.balls), 3)), np.zeros(3))
    out = {}
    for name, plan in (("old", OLD), ("new", NEW)):
        logs = []
        for k, poses in enumerate(_roles(plan)):
            data = simulate(machine, artefact, poses, truth, STYLUS_R, 0.5, seed=40 + k)
            logs.append(tmp_path / f"{name}{k}.csv")
            write_log(logs[-1], log_rows(data, artefact, run=f"r{k}"))
        assert main(["gap", "--log", str(logs[0]), "--holdout", str(logs[1]), "--machine",
                     str(MACHINE), "--artefact", str(ARTEFACT)]) == 0
        out[name] = capsys.readouterr().out
    assert ("warning: 2nd harmonic of C: the estimate poses give 2C only 3 distinct values; "
            "the validate poses extrapolate it") in out["old"]
    assert "shift_holdout_14poses.yaml" in out["old"]
    assert "harmonic of" not in out["new"] and "verdict:" in out["new"]


def test_rumba_plan_output_names_what_a_planned_holdout_cannot_identify(capsys):
    from daemon.cli.commands.plan import _harmonic_warnings

    machine, _ = load_machine(MACHINE)
    _harmonic_warnings(load_plan(OLD), machine)
    assert capsys.readouterr().out.startswith(
        "warning (rumba gap --holdout): 2nd harmonic of C: the estimate poses give 2C only 3 ")
    _harmonic_warnings(load_plan(NEW), machine)
    _harmonic_warnings(load_plan(CONFIG / "plans/thesis_ch3_7poses.yaml"), machine)  # no roles
    assert capsys.readouterr().out == ""
