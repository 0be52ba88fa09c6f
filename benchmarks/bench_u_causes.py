"""Where the link u's residual understatement comes from (issue 22 item 1): estimator or data.

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

    .venv/bin/python -m benchmarks.bench_u_causes synthetic 200
    .venv/bin/python -m benchmarks.bench_u_causes centres 100
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
from daemon.cli.commands.plan import make_plan
from identification.estimate import estimate
from identification.model import Centres, predict
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


def main(argv: tuple[str, ...] = ()) -> None:
    n = next((int(a) for a in argv if a.isdigit()), 100)
    (centres if "centres" in argv else synthetic)(n)


if __name__ == "__main__":
    main(tuple(sys.argv[1:]))
