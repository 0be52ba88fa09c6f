"""Warm-up during the morning check (issue 22): simulated runs of the 14-pose shift plan and of the
plan ``rumba plan`` optimises for it, the truth warming up along Z (simulators/thermal.py, τ =
15 min from cold) by 0, 5, 10 and 20 µm over the estimate's span, each analysed as the daemon
does (drift-aware, identification/drift.py) and by the plain estimate. Prints per plan and
warm-up: the share of (link, run) pairs within 2u of the truth with and without the drift model,
the mean link bias in u, how often the drift model was selected, the share of runs whose fitted
drift over the run is within 2u of the truth, the mean reported link u relative to the plain
estimate's (the null run's cost of the drift search), the drift-aware coverage's standard error
over runs, its mean signed error in u (bias), the spread of error/u (t_ν: √(ν/(ν−2)) before
issue 22's GUM-S1 u, 1 after), the median ν of σ, and the link u over today's (the u the
estimator stated before the t's ν/(ν−2) entered it: the issue's null-run criterion, ≤ 1.1).

``gap``: the gap diagnosis of a withheld warm-up 8 µm·(1 − e^(−t/900 s)) along Z on the
annex-B 14-pose plan (identification/gap/simlog.py touches, 0.5 µm trigger noise): how often it
is named ``thermal_drift:Z`` (exponential) and the held-out RMS after it over the noise floor.

    .venv/bin/python -m benchmarks.bench_warmup          (50 seeds per cell, ~10 min)
    .venv/bin/python -m benchmarks.bench_warmup 10       (10 seeds)
    .venv/bin/python -m benchmarks.bench_warmup gap 20   (the gap diagnosis, 20 seeds)
    .venv/bin/python -m benchmarks.bench_warmup 50 optimised   (one plan: shift | optimised)
"""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

import numpy as np
import yaml

from contracts.setup_files import load_artefact, load_machine
from daemon.analysis.identify import analyse_centres
from daemon.analysis.touch_centres import rows_to_centres
from daemon.cli.commands.plan import make_plan
from identification.estimate import estimate
from identification.uncertainty import t_variance_factor
from simulators.errors_schema import errors_from_dict
from simulators.offline import run_sync
from simulators.thermal import ThermalState
from simulators.truth import TruthModel

ROOT = Path(__file__).resolve().parents[1]
C = ROOT / "config"
MACHINE = C / "machines/thesis_wcbxfzyt.yaml"
ARTEFACT = C / "artefacts/thesis_4ball.yaml"
TARGETS = C / "plans/targets/shift_start.yaml"
ERRORS = C / "errors/thesis_tableB2.yaml"
TAU_S = 900.0
WARMUPS_UM = (0.0, 5.0, 10.0, 20.0)


def _truth(machine, mf, art, over_um: float, span_s: float) -> TruthModel:
    e = yaml.safe_load(ERRORS.read_text())
    if over_um:
        e["thermal"] = {"axes": {"Z": {"amplitude_um": ThermalState.amplitude_for(
            over_um, span_s, TAU_S), "tau_s": TAU_S}}}
    return TruthModel.build(machine, mf, art, errors_from_dict(e))


def cell(machine, mf, art, plan, text: str, over_um: float, span_s: float, seeds: int
         ) -> dict[str, float]:
    truth = _truth(machine, mf, art, over_um, span_s)
    want = {k: float(v) for k, v in truth.errors.links.items()}
    val = plan.indices("validate")
    cov_aware, cov_plain, bias, sel, drift_ok, u_ratio, over = [], [], [], [], [], [], []
    z_aware, run_cov, dof, u_today = [], [], [], []
    for seed in range(seeds):
        res = run_sync(truth, text, "fanuc", seed=2000 + seed)
        if res.state != "done":
            raise RuntimeError(f"seed {seed}: {res.state} {res.alarm}")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            data = rows_to_centres(res.rows, art, plan.stylus_radius_mm)
        a = analyse_centres(machine, art, data, validate_poses=val)
        est_c = data.centres.subset(~np.isin(data.centres.pose, val))
        pe = estimate(machine, art, est_c)
        plain = pe.links_si()
        # today's u before issue 22 item 1: the same covariance without the t's ν/(ν−2)
        old_f = np.sqrt(t_variance_factor(pe.sigma_dof))
        n0 = len(cov_aware)
        dof.append(a.estimation.sigma_dof or float("inf"))
        for k, v in a.links.items():
            cov_aware.append(abs(v.value - want.get(k, 0.0)) <= 2 * v.std)
            z_aware.append((v.value - want.get(k, 0.0)) / v.std)
            pv, pu, _ = plain[k]
            cov_plain.append(abs(pv - want.get(k, 0.0)) <= 2 * pu)
            bias.append((pv - want.get(k, 0.0)) / pu)
            u_ratio.append(v.std / pu)
            u_today.append(v.std / (pu / old_f))
        run_cov.append(np.mean(cov_aware[n0:]))
        th = a.thermal
        selected = th is not None and th.status == "selected"
        sel.append(selected)
        if over_um and truth.thermal is not None:
            true_z = truth.thermal.over_run_um(float(est_c.t_s.min()), float(est_c.t_s.max()))
            over.append(true_z["Z"])
            d = th.over_run_um.get("Z") if selected else None
            drift_ok.append(d is not None and abs(d.value - true_z["Z"]) <= 2 * d.std)
    z = np.array(z_aware)
    return {"cov_aware": float(np.mean(cov_aware)), "cov_plain": float(np.mean(cov_plain)),
            # the coverage's standard error over runs (a run's links are not independent)
            "cov_se": float(np.std(run_cov, ddof=1) / np.sqrt(len(run_cov))),
            "bias_aware_u": float(np.mean(z)), "z_std": float(np.std(z)),
            "dof": float(np.median(dof)), "u_today": float(np.mean(u_today)),
            "bias_plain_u": float(np.mean(np.abs(bias))), "selected": float(np.mean(sel)),
            "drift_ok": float(np.mean(drift_ok)) if drift_ok else float("nan"),
            "u_ratio": float(np.mean(u_ratio)), "over_um": float(np.mean(over)) if over
            else 0.0}


def _span(machine, mf, art, plan, text: str) -> float:
    """The estimate's span (first to last estimate-pose centre) of one drift-free run."""
    res = run_sync(_truth(machine, mf, art, 0.0, 1.0), text, "fanuc", seed=1)
    data = rows_to_centres(res.rows, art, plan.stylus_radius_mm)
    c = data.centres.subset(~np.isin(data.centres.pose, plan.indices("validate")))
    return float(c.t_s.max() - c.t_s.min())


def gap(seeds: int) -> None:
    from identification.effects import make_effect
    from identification.gap import diagnose
    from identification.gap.simlog import simulate
    from tests.gap_helpers import STYLUS_R, annex_b_setup, gap_truth

    machine, artefact, poses = annex_b_setup()
    eff = make_effect("thermal_drift", "Z", machine, model="exponential")
    named, exp, ratios, amp_ok = 0, 0, [], 0
    for seed in range(seeds):
        truth = gap_truth(artefact, seed=seed, effects=[(eff, np.array([8.0, 0.25]))])
        data = simulate(machine, artefact, poses, truth, STYLUS_R, 0.5, seed=seed)
        rep = diagnose(machine, artefact, data, STYLUS_R)
        v = rep["verdict"]
        ok = (v["effect"], v["axis"]) == ("thermal_drift", "Z")
        named += ok
        sel = v["selected"][0] if v["selected"] else {}
        exp += ok and sel.get("model") == "exponential"
        ratio = v["holdout_rms_after_um"] / rep["noise_floor_um"]
        ratios.append(ratio)
        a = sel.get("params", {}).get("drift_Z_amplitude")
        amp_ok += bool(a and abs(a["value"] - 8.0) <= 2 * a["std"])
        print(f"seed {seed}: {v['effect']}:{v['axis']} {sel.get('model', '')} after/floor "
              f"{ratio:.2f} {v['message'][:90]}", flush=True)
    r = np.array(ratios)
    print(f"withheld warm-up 8 µm·(1 − e^(−t/900 s)) Z, annex-B 14 poses, {seeds} seeds: named "
          f"thermal_drift:Z {named}/{seeds} (exponential {exp}), amplitude within 2u "
          f"{amp_ok}/{seeds}; held-out RMS after / floor median {np.median(r):.2f}, max "
          f"{r.max():.2f}, ≤ 1.5 in {int(np.sum(r <= 1.5))}/{seeds}")


def main(argv: tuple[str, ...] = ()) -> None:
    seeds = next((int(a) for a in argv if a.isdigit()), 50)
    if "gap" in argv:
        gap(seeds)
        return
    machine, mf = load_machine(MACHINE)
    art = load_artefact(ARTEFACT)
    r = make_plan(MACHINE, ARTEFACT, TARGETS, "fanuc")
    print(f"warm-up along Z, τ {TAU_S / 60:.0f} min from cold, {seeds} seeds per cell, "
          "Table B.2 links, thesis repeatability; 2u coverage over every (link, run)")
    print(f"{'plan':22s} {'warm-up':>8s} {'span':>6s} {'2u aware':>9s} {'2u plain':>9s} "
          f"{'|bias|/u plain':>15s} {'selected':>9s} {'drift in 2u':>12s} {'u/u_plain':>10s}"
          f" {'± se':>6s} {'bias/u':>7s} {'sd(z)':>6s} {'ν':>5s} {'u/u_today':>9s}")
    for label, plan, g in (("shift_start_14poses", r.reference, r.old),
                           (f"optimised ({len(r.plan.poses)} poses)", r.plan, r.new)):
        if ("shift" in argv or "optimised" in argv) and label.split("_")[0].split(" ")[0] \
                not in argv:
            continue  # one plan only (two processes on a loaded box)
        span = _span(machine, mf, art, plan, g.text)
        for over in WARMUPS_UM:
            x = cell(machine, mf, art, plan, g.text, over, span, seeds)
            ok = "" if over == 0 else f"{100 * x['drift_ok']:.0f}%"
            print(f"{label:22s} {over:6.0f}µm {span:5.0f}s {100 * x['cov_aware']:8.1f}% "
                  f"{100 * x['cov_plain']:8.1f}% {x['bias_plain_u']:15.2f} "
                  f"{100 * x['selected']:8.0f}% "
                  f"{ok:>12s} "
                  f"{x['u_ratio']:10.3f} {100 * x['cov_se']:5.1f}% {x['bias_aware_u']:+7.2f} "
                  f"{x['z_std']:6.2f} {x['dof']:5.1f} {x['u_today']:9.3f}", flush=True)


if __name__ == "__main__":
    main(tuple(sys.argv[1:]))
