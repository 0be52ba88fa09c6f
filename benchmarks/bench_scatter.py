"""Monte Carlo of the scatter-aware gap diagnosis, run by hand; prints the table:

    OMP_NUM_THREADS=1 nice .venv/bin/python benchmarks/bench_scatter.py [--seeds 50]

Thesis machine (Table B.2 links, random setup), 4-ball artefact, 0.5 µm touch noise, per-visit
index errors of B and C (1σ each) drawn by ``simlog.simulate``; three plans: the 14-pose shift
plan without repeats (shift-14: annex-B indexations + the drift-check revisit of the first pose,
one log, leave-one-pose-out), the annex-B plan with a hold-out (holdout-7+7: seven estimate
poses, the seven validate poses as a separate log) and the shipped hold-out plan (holdout-new:
config/plans/shift_holdout_14poses.yaml, the same indexations with interleaved roles). Per
condition and plan, over ``--seeds`` seeds:

* null runs at 5 / 10 / 15 µrad: share not ``unexplained``; share whose estimated B and C index
  repeatability are within 30 % of the truth (each axis, and their RMS); the bias of the
  estimate (mean, and the median ratio); the share whose stated ± u holds the truth within
  2u; coverage of the link errors' stated 2u (GLS under the estimated components); the runs
  attributing an effect that is not there; the share within 30 % of the run's OWN drawn RMS
  index error (14-15 draws per axis spread ±19 % around σ: what a run can know) and the mean
  ratio to it; the share whose 95 % likelihood interval holds σ. Every row (plan × σ) has its
  own seeds, whichever rows one process runs (``_row_seed``);
* a 40 µrad 2nd-harmonic C positioning error (random phase) under 8 µrad: share named
  ``rotary_positioning:C`` with the held-out RMS after it ≤ 1.5 × the scatter-aware held-out
  floor, the ratio to the floor of the model with it too, and which variant was named;
* a 5-20 µm step of one ball (random ball, moment, direction) under 10 µrad: share named with
  ball, moment (± one pose) and size (± 2 µm);
The shipped example log's verdict is checked by tests/test_gap_scatter.py.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from contracts.setup_files import load_artefact, load_machine, load_plan  # noqa: E402
from identification.effects import make_effect  # noqa: E402
from identification.gap import Options, diagnose  # noqa: E402
from identification.gap.selfcheck_scatter import knock, step_named  # noqa: E402
from identification.gap.simlog import Truth, index_errors_deg, simulate  # noqa: E402

TABLE_B2 = {"EB0Z": -12e-6, "EA0Y": -24e-6, "EC0Y": 17e-6, "EC0B": -23e-6, "EA0B": 2e-6,
            "EA0C": -19e-6, "EB0C": 26e-6, "EX0C": -0.106}
NOISE_UM = 0.5
STYLUS_R = 3.0


def _truth(artefact, seed: int, sigma: float) -> Truth:
    rng = np.random.default_rng(seed)
    base = base_truth_setup(artefact, rng)
    return Truth(dict(TABLE_B2), base[0], base[1], index_std_urad={"B": sigma, "C": sigma})


def base_truth_setup(artefact, rng):
    return rng.normal(0.0, 0.2, (len(artefact.balls), 3)), rng.normal(0.0, 0.05, 3)


def _run(machine, artefact, plans, name, truth, seed, options=None):
    poses, hold = plans[name]
    data = simulate(machine, artefact, poses, truth, STYLUS_R, NOISE_UM, seed=seed + 7919)
    hdata = None if hold is None else simulate(machine, artefact, hold, truth, STYLUS_R,
                                               NOISE_UM, seed=seed + 104729)
    return data, diagnose(machine, artefact, data, STYLUS_R, holdout=hdata, options=options)


def _links_covered(rep, truth) -> tuple[int, int]:
    ok = n = 0
    for name, v in rep["links"].items():
        k = 1e6 if name[1] in "ABC" else 1e3
        n += 1
        ok += abs(v["value"] - truth.links.get(name, 0.0) * k) <= 2 * v["std"]
    return ok, n


def _drawn_rms_urad(machine, plans, name, truth, seed) -> np.ndarray:
    """(2,) RMS of the index errors this run really drew for B and C over all its visits
    (training log and hold-out log): ``simulate`` draws them first from its generator."""
    poses, hold = plans[name]
    d = [index_errors_deg(machine, truth, len(poses), np.random.default_rng(seed + 7919))]
    if hold is not None:
        d.append(index_errors_deg(machine, truth, len(hold),
                                  np.random.default_rng(seed + 104729)))
    return np.sqrt(np.mean(np.deg2rad(np.vstack(d)) ** 2, axis=0)) * 1e6


PLAN_NAMES = ("shift-14", "holdout-7+7", "holdout-new")


def _row_seed(s: int, plan: str, sigma: float, offset: int) -> int:
    """Independent seeds per row of the null table (plan × σ, whichever rows one process
    runs): no two rows share a draw."""
    return 1000 * s + offset + 1_000_000 * (100 * PLAN_NAMES.index(plan) + round(sigma))


def _raw(on: bool, row: str, plan: str, seed: int, **values) -> None:
    if on:  # one line per run: a row split over processes is summed afterwards
        print("RUN " + json.dumps({"row": row, "plan": plan, "seed": seed, **values}),
              flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=50)
    ap.add_argument("--only", default="", help="comma list: null,interval,harmonic,step")
    ap.add_argument("--plans", default="", help="comma list: shift-14,holdout-7+7,holdout-new")
    ap.add_argument("--sigmas", default="5,10,15", help="null runs' index scatter, µrad")
    ap.add_argument("--first", type=int, default=0, help="first seed (split a row in parts)")
    ap.add_argument("--raw", action="store_true", help="also one JSON line per run (RUN …)")
    args = ap.parse_args()
    only = set(filter(None, args.only.split(","))) or {"null", "interval", "harmonic", "step"}
    machine, _ = load_machine(ROOT / "config/machines/thesis_wcbxfzyt.yaml")
    artefact = load_artefact(ROOT / "config/artefacts/thesis_4ball.yaml")
    annex = load_plan(ROOT / "config/plans/thesis_annexB_14poses.yaml")
    all_p = [(p.b_deg, p.c_deg) for p in annex.poses]
    est = [(p.b_deg, p.c_deg) for p in annex.poses if p.role == "estimate"]
    val = [(p.b_deg, p.c_deg) for p in annex.poses if p.role == "validate"]
    # holdout-new: the shipped hold-out plan, same indexations with interleaved roles so the
    # estimate poses give 2C all six values 0/60/…/300° (config/plans/shift_holdout_14poses.yaml)
    shp = load_plan(ROOT / "config/plans/shift_holdout_14poses.yaml")
    plans = {"shift-14": ([*all_p, all_p[0]], None), "holdout-7+7": (est, val),
             "holdout-new": ([(p.b_deg, p.c_deg) for p in shp.poses if p.role == "estimate"],
                             [(p.b_deg, p.c_deg) for p in shp.poses if p.role == "validate"])}
    plans = {k: v for k, v in plans.items() if k in (args.plans or k).split(",")}
    n = args.seeds
    t0 = time.perf_counter()
    runs = 0
    print(f"N = {n} seeds per condition and plan; touch noise {NOISE_UM} µm; index errors "
          f"drawn per visit for B and C")
    if "null" in only:
        print("\nnull runs: per-visit B/C index scatter only")
        print(f"{'plan':12s} {'σ µrad':>6s} {'not unexpl.':>11s} {'B ±30%':>7s} {'C ±30%':>7s} "
              f"{'RMS ±30%':>8s} {'bias B':>7s} {'bias C':>7s} {'med B/C':>9s} "
              f"{'B,C ±2u':>9s} {'2u cover':>8s} {'false':>5s} {'own ±30% B/C':>13s} "
              f"{'÷own B/C':>10s} {'ci95 B/C':>9s}")
        for name in plans:
            for sigma in (float(x) for x in args.sigmas.split(",")):
                acc = defaultdict(list)
                cov_ok = cov_n = 0
                for s in range(args.first, args.first + n):
                    seed = _row_seed(s, name, sigma, 3)
                    truth = _truth(artefact, seed, sigma)
                    _, rep = _run(machine, artefact, plans, name, truth, seed)
                    own = _drawn_rms_urad(machine, plans, name, truth, seed)
                    runs += 1
                    comps = {c["component"]: c for c in (rep["scatter"] or {}).get(
                        "components", [])}
                    sc = {k: c["sigma"] for k, c in comps.items()}
                    b, c = sc.get("index B", 0.0), sc.get("index C", 0.0)
                    for ax in "BC":  # the stated ± u of the component: does 2u hold σ?
                        u = (comps.get(f"index {ax}") or {}).get("std")
                        acc[f"u{ax}"].append(u is not None and abs(sc.get(f"index {ax}", 0.0)
                                                                   - sigma) <= 2 * u)
                    acc["ok"].append(rep["verdict"]["effect"] != "unexplained")
                    acc["false"].append(rep["verdict"]["effect"] not in ("none", "absorbed"))
                    acc["b"].append(abs(b - sigma) <= 0.3 * sigma)
                    acc["c"].append(abs(c - sigma) <= 0.3 * sigma)
                    acc["rms"].append(abs(np.hypot(b, c) / np.sqrt(2) - sigma) <= 0.3 * sigma)
                    acc["bb"].append(b / sigma - 1)
                    acc["bc"].append(c / sigma - 1)
                    # against the run's own drawn RMS: what a run of 14-15 visits can know
                    acc["ob"].append(abs(b - own[0]) <= 0.3 * own[0])
                    acc["oc"].append(abs(c - own[1]) <= 0.3 * own[1])
                    acc["rb"].append(b / own[0])
                    acc["rc"].append(c / own[1])
                    for ax in "BC":
                        ci = (comps.get(f"index {ax}") or {}).get("ci95")
                        acc[f"ci{ax}"].append(ci is not None and ci[0] <= sigma <= ci[1])
                    o, k = _links_covered(rep, truth)
                    cov_ok, cov_n = cov_ok + o, cov_n + k
                    _raw(args.raw, "null", name, s, sigma=sigma, b=b, c=c, cover=[o, k],
                         effect=rep["verdict"]["effect"], own=own.tolist(),
                         ci={a: (comps.get(f"index {a}") or {}).get("ci95") for a in "BC"},
                         u={a: (comps.get(f"index {a}") or {}).get("std") for a in "BC"})
                print(f"{name:12s} {sigma:6.0f} {100 * np.mean(acc['ok']):10.0f}% "
                      f"{100 * np.mean(acc['b']):6.0f}% {100 * np.mean(acc['c']):6.0f}% "
                      f"{100 * np.mean(acc['rms']):7.0f}% {100 * np.mean(acc['bb']):+6.0f}% "
                      f"{100 * np.mean(acc['bc']):+6.0f}% "
                      f"{1 + np.median(acc['bb']):4.2f}/{1 + np.median(acc['bc']):4.2f} "
                      f"{100 * np.mean(acc['uB']):3.0f}/{100 * np.mean(acc['uC']):3.0f}% "
                      f"{100 * cov_ok / cov_n:7.1f}% {int(np.sum(acc['false'])):5d} "
                      f"{100 * np.mean(acc['ob']):5.0f}/{100 * np.mean(acc['oc']):3.0f}% "
                      f"{np.mean(acc['rb']):4.2f}/{np.mean(acc['rc']):4.2f} "
                      f"{100 * np.mean(acc['ciB']):3.0f}/{100 * np.mean(acc['ciC']):3.0f}%",
                      flush=True)
    if "interval" in only:
        # The components' stated uncertainty alone (no candidates: the null runs' components
        # are the same unless an effect is selected): does σ̂ ± 2u, and the 95 % likelihood
        # interval, hold the true repeatability?
        print("\nnull runs, the index components' ± 2u and 95 % likelihood interval")
        print(f"{'plan':12s} {'σ µrad':>6s} {'B ±2u':>6s} {'C ±2u':>6s} {'B ci95':>7s} "
              f"{'C ci95':>7s} {'median B/C':>10s}")
        opt = Options(families=())
        for name in plans:
            for sigma in (float(x) for x in args.sigmas.split(",")):
                hit = defaultdict(list)
                for s in range(args.first, args.first + n):
                    truth = _truth(artefact, 1000 * s + 3, sigma)
                    _, rep = _run(machine, artefact, plans, name, truth, 1000 * s + 3, opt)
                    runs += 1
                    comps = {c["component"]: c for c in rep["scatter"]["components"]}
                    for ax in "BC":
                        c = comps[f"index {ax}"]
                        u, ci = c["std"], c["ci95"]
                        hit[f"u{ax}"].append(u is not None and abs(c["sigma"] - sigma) <= 2 * u)
                        hit[f"ci{ax}"].append(ci is not None and ci[0] <= sigma <= ci[1])
                        hit[f"r{ax}"].append(c["sigma"] / sigma)
                    _raw(args.raw, "interval", name, s, sigma=sigma,
                         comps={ax: comps[f"index {ax}"] for ax in "BC"})
                print(f"{name:12s} {sigma:6.0f} " + " ".join(
                    f"{100 * np.mean(hit[k]):5.0f}%" for k in ("uB", "uC", "ciB", "ciC"))
                      + f" {np.median(hit['rB']):5.2f}/{np.median(hit['rC']):4.2f}", flush=True)
    if "harmonic" in only:
        print("\n40 µrad 2nd-harmonic C positioning error under 8 µrad B/C index scatter")
        print(f"{'plan':12s} {'named':>6s} {'≤1.5 floor':>10s} {'both':>6s} "
              f"{'after/floor median':>18s} {'max':>6s} {'/own floor med':>14s} {'max':>6s}"
              "  models named")
        eff = make_effect("rotary_positioning", "C", machine)
        for name in plans:
            named, under, both, ratio, own = [], [], [], [], []
            models: dict[str, int] = defaultdict(int)
            for s in range(args.first, args.first + n):
                truth = _truth(artefact, 1000 * s + 5, 8.0)
                ph = np.random.default_rng(s).uniform(0, 2 * np.pi)
                truth.effects = [(eff, np.array([0, 0, 0, 40 * np.cos(ph), 40 * np.sin(ph)]))]
                _, rep = _run(machine, artefact, plans, name, truth, 1000 * s + 5)
                runs += 1
                v = rep["verdict"]
                r = v["holdout_rms_after_um"] / rep["noise"]["holdout_floor_um"]
                nm = (v["effect"], v["axis"]) == ("rotary_positioning", "C")
                # …and against the floor of the model with it (its own parameters' prediction
                # variance on the held-out poses included)
                own.append(v["holdout_rms_after_um"] / v["holdout_floor_after_um"])
                if nm:
                    models[v["selected"][0].get("model", "slope + harmonics 1-2")] += 1
                _raw(args.raw, "harmonic", name, s, named=nm, ratio=r, own=own[-1],
                     model=v["selected"][0].get("model") if nm else None)
                named.append(nm)
                under.append(r <= 1.5)
                both.append(nm and r <= 1.5)
                ratio.append(r)
            print(f"{name:12s} {100 * np.mean(named):5.0f}% {100 * np.mean(under):9.0f}% "
                  f"{100 * np.mean(both):5.0f}% {np.median(ratio):18.2f} {np.max(ratio):6.2f} "
                  f"{np.median(own):14.2f} {np.max(own):6.2f}  {dict(models)}", flush=True)
    if "step" in only:
        print("\n5-20 µm step of one ball under 10 µrad B/C index scatter")
        print(f"{'plan':12s} {'named':>6s} {'size err median µm':>18s} {'max':>6s}")
        for name in [k for k in plans if k == "shift-14"]:
            named, err = [], []
            for s in range(args.first, args.first + n):
                truth = _truth(artefact, 1000 * s + 7, 10.0)
                poses = plans[name][0]
                kb = knock(np.random.default_rng(s + 77), len(artefact.balls), len(poses))
                truth.ball_steps = [(kb.ball, kb.t_s, kb.vector_mm)]
                _, rep = _run(machine, artefact, plans, name, truth, 1000 * s + 7)
                runs += 1
                named.append(step_named(rep, kb, artefact.ids))
                if rep.get("ball_step"):
                    err.append(abs(rep["ball_step"]["size_um"] - kb.size_um))
                _raw(args.raw, "step", name, s, named=named[-1],
                     err=err[-1] if rep.get("ball_step") else None)
            print(f"{name:12s} {100 * np.mean(named):5.0f}% "
                  f"{np.median(err) if err else float('nan'):18.2f} "
                  f"{max(err) if err else float('nan'):6.2f}", flush=True)
    dt = time.perf_counter() - t0
    print(f"\n{runs} diagnoses in {dt:.0f} s ({dt / max(runs, 1):.2f} s each)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
