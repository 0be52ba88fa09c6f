"""Where the link u's residual understatement comes from: estimator or data.

Two measurements, both on the thesis machine and the 14-pose shift plan, drift-free:

``synthetic``: the estimate's own calibration. Centres drawn i.i.d. Gaussian per axis (the
thesis §3.4 repeatability 0.66 / 0.98 / 0.44 µm) around the exact model prediction of one
simulated run's poses, estimated as the daemon does (a posteriori σ per axis, GUM-S1 u) and with
the true σ given: the spread of error/u per link and the 2u coverage. A spread of 1 (within its
bootstrap standard error) says the estimator states u right for data that meet its assumptions.

``centres``: whether the simulator's centres meet them. Each run's centres minus those of the
same program on a noise-free truth: the standard deviation per axis (against the stated
repeatability), Bartlett's test of equal variance over the centres of an axis, the correlation
between any two centres (touch noise and per-visit centre scatter must leave them independent)
and the mean error per centre (a bias of the sphere fit shows as |t| > 3).

``links``: whether the u is allocated right per link on the simulator's own runs. Each run its
own truth and noise (bench_warmup's seeds, no index scatter, no warm-up), estimated with the
true σ given and independent centres: sd(error/u) per link, with the same spread for i.i.d.
centres drawn around that run's estimate on the same poses (the estimator's share).

    .venv/bin/python -m benchmarks.bench_u_causes synthetic 200
    .venv/bin/python -m benchmarks.bench_u_causes centres 100
    .venv/bin/python -m benchmarks.bench_u_causes links 100
"""

from __future__ import annotations

import functools
import sys
import warnings

import numpy as np
import yaml
from scipy.stats import bartlett

from benchmarks.bench_warmup import ARTEFACT, ERRORS, MACHINE, TARGETS
from contracts.setup_files import load_artefact, load_machine
from daemon.analysis.touch_centres import rows_to_centres
from identification.estimate import estimate
from identification.model import Centres, predict
from programs.plan_make import make_plan
from simulators.errors_schema import errors_from_dict
from simulators.offline import run_sync
from simulators.truth import TruthModel

THESIS_SIGMA_UM = np.array([0.66, 0.98, 0.44])  # thesis §3.4 centre repeatability x, y, z


@functools.cache
def _setup() -> tuple:
    machine, mf = load_machine(MACHINE)
    return machine, mf, load_artefact(ARTEFACT), make_plan(MACHINE, ARTEFACT, TARGETS, "fanuc")


def _run_centres(noise: bool, seed: int) -> Centres:
    machine, mf, art, plan = _setup()
    e = yaml.safe_load(ERRORS.read_text())
    if not noise:
        e["probe"]["centre_noise_um"] = [0.0, 0.0, 0.0]
        e["probe"]["touch_noise_um"] = 0.0
    truth = TruthModel.build(machine, mf, art, errors_from_dict(e))
    res = run_sync(truth, plan.old.text, "fanuc", seed=seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return rows_to_centres(res.rows, art, plan.reference.stylus_radius_mm).centres


def _spread(z: np.ndarray, rng: np.random.Generator) -> tuple[float, float]:
    """sd(z) over every (run, link) and its bootstrap standard error over runs."""
    boot = [z[rng.integers(0, len(z), len(z))].std() for _ in range(200)]
    return float(z.std()), float(np.std(boot))


def synthetic(runs: int) -> None:
    machine, _, art, plan = _setup()
    c0 = _run_centres(True, 2000)  # the estimate's poses, as bench_warmup fits them
    c0 = c0.subset(~np.isin(c0.pose, plan.reference.indices("validate")))
    e0 = estimate(machine, art, c0)
    p_true = e0.p  # any point near the truth: the data are generated from it exactly
    pred, _ = predict(machine, art, e0.layout, p_true, c0)
    sig_mm = THESIS_SIGMA_UM * 1e-3
    rng = np.random.default_rng(7)
    n_l = len(e0.layout.links)
    z: dict[str, list[np.ndarray]] = {"a posteriori": [], "σ given": []}
    for _ in range(runs):
        xyz = pred + rng.normal(0.0, 1.0, pred.shape) * sig_mm
        c = Centres(c0.pose, c0.ball, c0.b_deg, c0.c_deg, xyz, c0.t_s)
        for label, kw in (("a posteriori", {}), ("σ given", {"sigma_um": THESIS_SIGMA_UM})):
            e = estimate(machine, art, c, **kw)
            z[label].append(((e.p - p_true) / e.std)[:n_l])
    print(f"synthetic i.i.d. centres, {runs} runs, {len(c0)} centres, {n_l} links "
          f"{list(e0.layout.links)}")
    for label, zl in z.items():
        za = np.array(zl)
        sd, se = _spread(za, rng)
        print(f"  {label:13s} 2u coverage {100 * np.mean(np.abs(za) <= 2):5.1f} %  sd(error/u) "
              f"{sd:.3f} ± {se:.3f}  per link " + " ".join(f"{s:.2f}" for s in za.std(0)))


def centres(runs: int) -> None:
    c0 = _run_centres(False, 1)
    errs = []
    for s in range(runs):
        c = _run_centres(True, 2000 + s)
        if len(c) != len(c0) or np.any(c.pose != c0.pose) or np.any(c.ball != c0.ball):
            raise RuntimeError(f"seed {2000 + s}: not the noise-free run's centres")
        errs.append((c.xyz_mm - c0.xyz_mm) * 1e3)
    e = np.array(errs)
    k = e.shape[1]
    print(f"simulator centre errors, {runs} runs x {k} centres: sd per axis "
          f"{np.round(e.reshape(-1, 3).std(0), 3)} µm (stated {THESIS_SIGMA_UM})")
    for a in range(3):
        corr = np.corrcoef(e[:, :, a].T)[~np.eye(k, dtype=bool)]
        p = bartlett(*[e[:, j, a] for j in range(k)]).pvalue
        print(f"  {'xyz'[a]}: equal variance over centres p = {p:.3f}; centre-centre "
              f"correlation mean {corr.mean():+.4f}, max |r| {np.abs(corr).max():.3f} "
              f"(independent: sd {1 / np.sqrt(runs):.3f})")
    t = e.mean(0) / (e.std(0) / np.sqrt(runs))
    print(f"  mean error per centre: |t| > 3 in {int(np.sum(np.abs(t) > 3))} of {t.size}")


def links(runs: int) -> None:
    from benchmarks.bench_warmup import run_seed

    machine, mf, art, plan = _setup()
    e = errors_from_dict(yaml.safe_load(ERRORS.read_text()))
    val = plan.reference.indices("validate")
    rng = np.random.default_rng(5)
    zs, zi = [], []
    for i in range(runs):
        seed = run_seed("links", 0.0, i)
        truth = TruthModel.build(machine, mf, art, e, seed=seed)
        res = run_sync(truth, plan.old.text, "fanuc", seed=seed)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            c = rows_to_centres(res.rows, art, plan.reference.stylus_radius_mm).centres
        c = c.subset(~np.isin(c.pose, val))
        est = estimate(machine, art, c, sigma_um=THESIS_SIGMA_UM, visit_scatter=False)
        si = est.links_si()
        zs.append([(si[k][0] - float(truth.errors.links.get(k, 0.0))) / si[k][1]
                   for k in est.layout.links])
        pred, _ = predict(machine, art, est.layout, est.p, c)
        xyz = pred + rng.normal(size=pred.shape) * THESIS_SIGMA_UM * 1e-3
        e2 = estimate(machine, art, Centres(c.pose, c.ball, c.b_deg, c.c_deg, xyz, c.t_s),
                      sigma_um=THESIS_SIGMA_UM, visit_scatter=False)
        zi.append(((e2.p - est.p) / e2.std)[: len(est.layout.links)])
    print(f"sd(error/u) per link, true σ given, {runs} simulated shift runs (se ≈ "
          f"{1 / np.sqrt(2 * runs):.2f})")
    for label, z in (("simulated", np.array(zs)), ("i.i.d.", np.array(zi))):
        print(f"  {label:10s} " + " ".join(f"{k} {s:.2f}" for k, s in
                                           zip(est.layout.links, z.std(0), strict=True)))


def main(argv: tuple[str, ...] = ()) -> None:
    n = next((int(a) for a in argv if a.isdigit()), 100)
    (centres if "centres" in argv else links if "links" in argv else synthetic)(n)


if __name__ == "__main__":
    main(tuple(sys.argv[1:]))
