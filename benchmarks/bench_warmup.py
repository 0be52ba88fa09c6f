"""Warm-up during the morning check: Monte Carlo of the drift-aware estimate.

Simulated runs of the 14-pose shift plan and of the plan ``rumba plan`` optimises for it, on the
thesis machine (Table B.2 links, thesis touch and centre repeatability) with the rotary axes'
index scatter (``INDEX_URAD`` 1σ on B and C per indexation) and a warm-up from cold
δ(t) = A·(1 − e^(−t/τ)) (simulators/thermal.py) whose drift over the estimate's span is 0, 5, 10
or 20 µm, τ drawn log-uniform in 10-60 min and the direction uniform on the sphere (one τ for
the three axes: one thermal state). Every run draws its own seed, a hash of (plan, warm-up,
index): no two cells share noise. The machine file states the rotary repeatability a shop's
would (the maker's spec, ``STATED_URAD`` on B and C; ``stated=0``: none, ``stated=2``: a wrong
data sheet), the Type B input of the index components (identification/estimate_scatter.py).
Each run is analysed as the daemon does (drift-aware, identification/drift.py) and by the plain
estimate. Prints per plan, warm-up and stated repeatability:

- 2u coverage over every (link, run) pair, drift-aware and plain, each with its binomial
  standard error (pairs as if independent) and its run-clustered one (the links of a run share
  its σ̂ and its drift fit: the standard deviation of the per-run coverage over √N);
- bias: the mean (estimate − truth)/u of the drift-aware links, ± its clustered standard error,
  and sd(z) the spread of (estimate − truth)/u;
- how often a drift model was selected (on the null rows: falsely), the share of fitted
  (run, axis) drifts over the run within 2u of the truth, the share of (run, axis) with a true
  drift ≥ 2 µm the selected model left out;
- u/u_plain, the reported link u over the plain estimate's (the cost of the drift search), and
  u/u_today, over the u stated w/o scatter, drift (independent centres, no t's ν/(ν−2)): the
  issue's null-run criterion, ≤ 1.1 (mean over links; the summary also prints the worst link's).

``gap``: the gap diagnosis of a withheld warm-up 8 µm·(1 − e^(−t/900 s)) along Z (or X, Y) on the
annex-B 14-pose plan (identification/gap/simlog.py touches, 0.5 µm trigger noise): how often it
is named ``thermal_drift:Z`` (exponential) and the held-out RMS after it over the noise floor.

    .venv/bin/python -m benchmarks.bench_warmup 200          (200 runs per cell, ~1 h per plan)
    .venv/bin/python -m benchmarks.bench_warmup 50 optimised   (one plan: shift | optimised)
    .venv/bin/python -m benchmarks.bench_warmup 200 shift 0 5  (some warm-ups only, µm)
    .venv/bin/python -m benchmarks.bench_warmup 50 shift 0 index=0   (no index scatter)
    .venv/bin/python -m benchmarks.bench_warmup 50 shift out=r.jsonl  (appends; re-run resumes)
    .venv/bin/python -m benchmarks.bench_warmup 50 shift 0 10 stated=2  (a wrong data sheet)
    .venv/bin/python -m benchmarks.bench_warmup gap 50 X (the gap diagnosis, 50 seeds, along X)
    .venv/bin/python -m benchmarks.bench_warmup gap 50 X from=11  (seeds 11-49 only)
"""

from __future__ import annotations

import hashlib
import json
import math
import sys
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import yaml

from contracts.setup_files import load_artefact, load_machine
from daemon.analysis.identify import analyse_centres
from daemon.analysis.touch_centres import rows_to_centres
from identification.estimate import estimate
from identification.uncertainty import t_variance_factor
from programs.plan_make import make_plan
from simulators.errors_schema import errors_from_dict
from simulators.offline import run_sync
from simulators.thermal import AxisWarmup, ThermalState
from simulators.truth import TruthModel

ROOT = Path(__file__).resolve().parents[1]
C = ROOT / "config"
MACHINE = C / "machines/thesis_wcbxfzyt.yaml"
ARTEFACT = C / "artefacts/thesis_4ball.yaml"
TARGETS = C / "plans/targets/shift_start.yaml"
ERRORS = C / "errors/thesis_tableB2.yaml"
TAU_RANGE_S = (600.0, 3600.0)  # the 10-60 min (ISO 230-3), drawn log-uniform
INDEX_URAD = 4.0  # B and C index repeatability 1σ: R = 4σ ≈ 16 µrad (3.3″), a good trunnion
STATED_URAD = 4.0  # what the machine file states for B and C: the maker's spec, the truth's
WARMUPS_UM = (0.0, 5.0, 10.0, 20.0)
MISSED_UM = 2.0  # a true drift component this large the selected model should carry


def run_seed(plan: str, over_um: float, i: int) -> int:
    """The run's seed: a hash of (plan, warm-up, index), so no two cells share noise draws
    (Python's ``hash`` is salted per process: not reproducible)."""
    h = hashlib.sha256(f"{plan}|{over_um:g}|{i}".encode()).digest()
    return int.from_bytes(h[:4], "little")


def draw_warmup(seed: int, over_um: float, span_s: float) -> ThermalState | None:
    """The run's thermal state: τ log-uniform in ``TAU_RANGE_S``, a direction uniform on the
    sphere, amplitudes such that the drift over ``span_s`` from cold is ``over_um`` along it.
    Built directly, not through the errors file: 20 µm over the optimised plan's 101 s with
    τ = 60 min needs A ≈ 720 µm, past the file's ±500 µm (an over-run drift that large comes
    from a fast warm-up; over so short a run only its curvature depends on τ)."""
    if not over_um:
        return None
    rng = np.random.default_rng([seed, 22])
    tau = float(math.exp(rng.uniform(*np.log(TAU_RANGE_S))))
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    amp = ThermalState.amplitude_for(over_um, span_s, tau)
    return ThermalState({a: AxisWarmup(float(amp * d[k]), tau) for k, a in enumerate("XYZ")})


def _truth(machine, mf, art, thermal: ThermalState | None, seed: int,
           index_urad: float = INDEX_URAD) -> TruthModel:
    e = yaml.safe_load(ERRORS.read_text())
    if index_urad:
        e["indexing"] = {"repeatability_urad": {"B": index_urad, "C": index_urad}}
    # the truth's seed drives the index scatter draws (simulators/visit_errors.py)
    truth = TruthModel.build(machine, mf, art, errors_from_dict(e), seed=seed)
    return truth if thermal is None else replace(truth, thermal=thermal)


def _se(per_run: list[float]) -> float:
    """Run-clustered standard error of a mean over runs (equal cluster sizes)."""
    return float(np.std(per_run, ddof=1) / np.sqrt(len(per_run))) if len(per_run) > 1 else 0.0


def run_one(machine, mf, art, plan, text: str, name: str, over_um: float, span_s: float,
            i: int, index_urad: float = INDEX_URAD, stated_urad: float = STATED_URAD) -> dict:
    """Run ``i`` of the cell (plan ``name``, warm-up ``over_um``): per link whether it is within
    2u (drift-aware, plain), its error/u and u ratios; the drift selection and fit. The seed
    does not depend on ``stated_urad``: cells that differ in it share their runs' noise."""
    seed = run_seed(name, over_um, i)
    truth = _truth(machine, mf, art, draw_warmup(seed, over_um, span_s), seed, index_urad)
    want = {k: float(v) for k, v in truth.errors.links.items()}
    res = run_sync(truth, text, "fanuc", seed=seed)
    if res.state != "done":
        raise RuntimeError(f"{name} {over_um} µm run {i} (seed {seed}): {res.state} {res.alarm}")
    val = plan.indices("validate")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        data = rows_to_centres(res.rows, art, plan.stylus_radius_mm)
    stated = {"B": stated_urad, "C": stated_urad} if stated_urad else None
    a = analyse_centres(machine, art, data, validate_poses=val, rotary_repeatability_urad=stated)
    est_c = data.centres.subset(~np.isin(data.centres.pose, val))
    pe = estimate(machine, art, est_c, rotary_repeatability_urad=stated)
    plain = pe.links_si()
    # today's u, without visit scatter, drift: independent centres, a posteriori σ per axis, no t's
    # ν/(ν−2) (the visit sandwich engaged only past its test, ~7 % of scatter-free runs)
    pi = estimate(machine, art, est_c, visit_scatter=False)
    today = {k: u / float(np.sqrt(t_variance_factor(pi.sigma_dof)))
             for k, (_, u, _) in pi.links_si().items()}
    # the axes whose stated repeatability the run overrode: the estimator's own decision
    overridden = [x for x in (a.estimation.index_scatter or ())
                  if x.stated_urad is not None and x.used == "estimated"]
    rec: dict = {"plan": name, "warmup_um": over_um, "i": i, "seed": seed,
                 "stated_urad": stated_urad,
                 "overridden": len(overridden),
                 "dof": a.estimation.sigma_dof or float("inf"), "aware": [], "plain": [],
                 "z": [], "u_ratio": [], "u_today": [], "drift": [], "missed": [],
                 "over_um": 0.0, "index_urad": {k: v[0] for k, v in (pe.visit_scatter or {}).items()
                                                if k.startswith("index")}}
    for k, v in a.links.items():
        err = v.value - want.get(k, 0.0)
        pv, pu, _ = plain[k]
        rec["aware"].append(bool(abs(err) <= 2 * v.std))
        rec["z"].append(err / v.std)
        rec["plain"].append(bool(abs(pv - want.get(k, 0.0)) <= 2 * pu))
        rec["u_ratio"].append(v.std / pu)
        rec["u_today"].append(v.std / today[k])
    th = a.thermal
    rec["selected"] = bool(th is not None and th.status == "selected")
    if over_um and truth.thermal is not None:
        true = truth.thermal.over_run_um(float(est_c.t_s.min()), float(est_c.t_s.max()))
        rec["over_um"] = float(np.linalg.norm(list(true.values())))
        rec["tau_s"] = truth.thermal.axes["X"].tau_s
        fitted = th.over_run_um if rec["selected"] else {}
        for ax, tv in true.items():
            d = fitted.get(ax)
            if d is not None:  # a fitted axis: its drift over the run within 2u
                rec["drift"].append(bool(abs(d.value - tv) <= 2 * d.std))
            if abs(tv) >= MISSED_UM:  # a sizeable true drift the model left out
                rec["missed"].append(d is None)
    return rec


def summarise(recs: list[dict]) -> dict:
    """One cell's figures from its runs (see the module doc)."""
    n = len(recs)
    aware = [float(np.mean(r["aware"])) for r in recs]
    plain = [float(np.mean(r["plain"])) for r in recs]
    zrun = [float(np.mean(r["z"])) for r in recs]
    z = np.concatenate([r["z"] for r in recs])
    drift = [x for r in recs for x in r["drift"]]
    missed = [x for r in recs for x in r["missed"]]
    p_a, p_p = float(np.mean(aware)), float(np.mean(plain))
    return {"plan": recs[0]["plan"], "warmup_um": recs[0]["warmup_um"], "runs": n,
            "stated_urad": recs[0].get("stated_urad", 0.0),
            "overridden": float(np.mean([r.get("overridden", 0) > 0 for r in recs])),
            "links": len(z) // n,
            "cov_aware": p_a, "cov_aware_se_binom": math.sqrt(p_a * (1 - p_a) / len(z)),
            "cov_aware_se_run": _se(aware),
            "cov_plain": p_p, "cov_plain_se_binom": math.sqrt(p_p * (1 - p_p) / len(z)),
            "cov_plain_se_run": _se(plain),
            "bias_u": float(np.mean(z)), "bias_se_run": _se(zrun), "z_std": float(np.std(z)),
            "dof": float(np.median([r["dof"] for r in recs])),
            "selected": float(np.mean([r["selected"] for r in recs])),
            "drift_ok": float(np.mean(drift)) if drift else float("nan"),
            "drift_pairs": len(drift),
            "missed": float(np.mean(missed)) if missed else float("nan"),
            "u_ratio": float(np.mean(np.concatenate([r["u_ratio"] for r in recs]))),
            "u_today": float(np.mean(np.concatenate([r["u_today"] for r in recs]))),
            "u_today_max": float(np.max(np.mean([r["u_today"] for r in recs], axis=0))),
            "over_um": float(np.mean([r["over_um"] for r in recs]))}


def _span(machine, mf, art, plan, text: str) -> float:
    """The estimate's span (first to last estimate-pose centre) of one drift-free run."""
    res = run_sync(_truth(machine, mf, art, None, 1), text, "fanuc", seed=1)
    data = rows_to_centres(res.rows, art, plan.stylus_radius_mm)
    c = data.centres.subset(~np.isin(data.centres.pose, plan.indices("validate")))
    return float(c.t_s.max() - c.t_s.min())


def gap(seeds: int, axis: str = "Z", first: int = 0) -> None:
    """The withheld warm-up 8 µm·(1 − e^(−t/900 s)) along ``axis`` (module doc)."""
    from benchmarks.rigs.gap_helpers import STYLUS_R, annex_b_setup, gap_truth
    from identification.effects import make_effect
    from identification.gap import diagnose
    from identification.gap.simlog import simulate

    machine, artefact, poses = annex_b_setup()
    eff = make_effect("thermal_drift", axis, machine, model="exponential")
    named, exp, ratios, amp_ok = 0, 0, [], 0
    for seed in range(first, seeds):
        truth = gap_truth(artefact, seed=seed, effects=[(eff, np.array([8.0, 0.25]))])
        data = simulate(machine, artefact, poses, truth, STYLUS_R, 0.5, seed=seed)
        rep = diagnose(machine, artefact, data, STYLUS_R)
        v = rep["verdict"]
        ok = (v["effect"], v["axis"]) == ("thermal_drift", axis)
        named += ok
        sel = v["selected"][0] if v["selected"] else {}
        exp += ok and sel.get("model") == "exponential"
        ratio = v["holdout_rms_after_um"] / rep["noise_floor_um"]
        ratios.append(ratio)
        a = sel.get("params", {}).get(f"drift_{axis}_amplitude")
        amp_ok += bool(a and abs(a["value"] - 8.0) <= 2 * a["std"])
        amp = f"A {a['value']:.2f} ± {a['std']:.2f} µm" if a else "A —"
        print(f"seed {seed}: {v['effect']}:{v['axis']} {sel.get('model', '')} after/floor "
              f"{ratio:.2f} {amp} {v['message'][:90]}", flush=True)
    r = np.array(ratios)
    n = seeds - first
    print(f"withheld warm-up 8 µm·(1 − e^(−t/900 s)) {axis}, annex-B 14 poses, seeds {first}-"
          f"{seeds - 1}: named thermal_drift:{axis} {named}/{n} (exponential {exp}), amplitude "
          f"within 2u {amp_ok}/{n}; held-out RMS after / floor median {np.median(r):.2f}, max "
          f"{r.max():.2f}, ≤ 1.5 in {int(np.sum(r <= 1.5))}/{n}")


def _row(x: dict) -> str:
    ok = "" if not x["warmup_um"] else f"{100 * x['drift_ok']:.1f}%"
    miss = "" if not x["warmup_um"] else f"{100 * x['missed']:.1f}%"
    return (f"{x['plan']:22s} {x['warmup_um']:5.0f}µm {x['stated_urad']:4.0f} "
            f"{100 * x['overridden']:4.0f}% {x['over_um']:6.1f} "
            f"{100 * x['cov_aware']:6.1f}% ±{100 * x['cov_aware_se_binom']:.1f}/"
            f"{100 * x['cov_aware_se_run']:.1f} "
            f"{100 * x['cov_plain']:6.1f}% ±{100 * x['cov_plain_se_binom']:.1f}/"
            f"{100 * x['cov_plain_se_run']:.1f} "
            f"{x['bias_u']:+6.3f}±{x['bias_se_run']:.3f} {x['z_std']:5.2f} "
            f"{100 * x['selected']:6.1f}% {ok:>7s} {miss:>7s} "
            f"{x['u_ratio']:7.3f} {x['u_today']:7.3f} {x['u_today_max']:7.3f} {x['dof']:5.1f}")


def _print_table(recs: list[dict]) -> None:
    print(f"{'plan':22s} {'warm':>7s} {'said':>4s} {'over':>5s} {'|δ|':>6s} {'2u aware':>17s} "
          f"{'2u plain':>17s} "
          f"{'bias/u ± se':>12s} {'sd(z)':>5s} {'select':>7s} {'δ in 2u':>7s} {'missed':>7s} "
          f"{'u/plain':>7s} {'u/today':>7s} {'max':>7s} {'ν':>5s}   N")
    cells: dict[tuple[str, float, float], list[dict]] = {}
    for r in recs:
        cells.setdefault((r["plan"], r["warmup_um"], r.get("stated_urad", 0.0)), []).append(r)
    for key in sorted(cells, key=lambda k: (not k[0].startswith("shift"), k[1], -k[2])):
        x = summarise(cells[key])
        print(_row(x) + f" {x['runs']:4d}", flush=True)


def main(argv: tuple[str, ...] = ()) -> None:
    nums = [a for a in argv if a.replace(".", "", 1).isdigit()]
    runs = int(nums[0]) if nums else 50
    if "gap" in argv:
        gap(runs, next((a for a in argv if a in ("X", "Y", "Z")), "Z"),
            next((int(a[5:]) for a in argv if a.startswith("from=")), 0))
        return
    if "summary" in argv:  # the table of a record file written by ``out=``
        path = Path(argv[-1])
        _print_table([json.loads(line) for line in path.read_text().splitlines() if line])
        return
    warmups = tuple(float(a) for a in nums[1:]) or WARMUPS_UM
    index_urad = next((float(a[6:]) for a in argv if a.startswith("index=")), INDEX_URAD)
    stated = next((float(a[7:]) for a in argv if a.startswith("stated=")), STATED_URAD)
    out = next((Path(a[4:]) for a in argv if a.startswith("out=")), None)
    machine, mf = load_machine(MACHINE)
    art = load_artefact(ARTEFACT)
    r = make_plan(MACHINE, ARTEFACT, TARGETS, "fanuc")
    print(f"{runs} independent runs per cell; warm-up from cold, τ log-uniform "
          f"{TAU_RANGE_S[0] / 60:.0f}-{TAU_RANGE_S[1] / 60:.0f} min, direction uniform; index "
          f"scatter {index_urad:g} µrad 1σ on B and C, stated "
          f"{f'{stated:g} µrad' if stated else 'none'}; Table B.2 links, thesis repeatability. "
          "Coverage ± binomial / run-clustered se", flush=True)
    plans = []
    for name, plan, g in (("shift_start_14poses", r.reference, r.old),
                          (f"optimised_{len(r.plan.poses)}poses", r.plan, r.new)):
        if ("shift" in argv or "optimised" in argv) and not any(
                name.startswith(a) for a in argv):
            continue  # one plan only (one process per core)
        plans.append((name, plan, g.text, _span(machine, mf, art, plan, g.text)))
    recs: list[dict] = []
    done: set[tuple[str, float, int, float]] = set()
    if out is not None and out.exists():  # resume: the runs already in the record file
        recs = [json.loads(line) for line in out.read_text().splitlines() if line]
        done = {(r["plan"], r["warmup_um"], r["i"], r.get("stated_urad", 0.0)) for r in recs}
    # run i of every cell before run i + 1 of any: stopped early, the cells have equal N
    for i in range(runs):
        for name, plan, text, span in plans:
            for over in warmups:
                if (name, over, i, stated) in done:
                    continue
                rec = run_one(machine, mf, art, plan, text, name, over, span, i, index_urad,
                              stated)
                recs.append(rec)
                if out is not None:
                    with out.open("a") as f:
                        f.write(json.dumps(rec) + "\n")
    _print_table(recs)


if __name__ == "__main__":
    main(tuple(sys.argv[1:]))
