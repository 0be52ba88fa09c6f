"""Whether ``rumba plan``'s predicted link u hold under rotary index scatter.

The thesis machine (Table B.2 links, thesis touch and centre repeatability 0.66 / 0.98 / 0.44
µm) with every indexation of B and C stopping ``index`` µrad 1σ off (the simulator's
``indexing.repeatability_urad``), and a machine file that states it. For each plan: the
simulator runs it ``N`` times (its own seed each), the run is estimated as the daemon does with
σ given and the stated repeatability, and the error of every link against the truth is
compared with the optimiser's predicted u — stated (the visit sandwich, ``programs.design``)
and as it was before (nothing stated: exact indexing). Plans: ``optimised-stated`` (what
`rumba plan` chooses with the stated value), ``optimised-none`` (what it chose before, from a
machine file stating nothing) and the shipped ``shift_start_14poses``.

    .venv/bin/python -m benchmarks.bench_plan_index [N] [index_urad] [plan name …]

Per link: rms error / predicted u (stated, and nothing stated) with its standard error
(≈ ratio/√(2N)), and the share of runs within 2 predicted u.
"""

from __future__ import annotations

import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np
import yaml

from contracts.setup_files import load_artefact, load_machine, load_plan
from daemon.analysis.touch_centres import rows_to_centres
from identification.estimate import estimate
from programs.generate import generate
from programs.plan_make import make_plan
from programs.plan_report import plan_links, predicted_u
from simulators.errors_schema import errors_from_dict
from simulators.offline import run_sync
from simulators.truth import TruthModel

ROOT = Path(__file__).resolve().parent.parent
CONFIG = ROOT / "config"
MACHINE = CONFIG / "machines" / "thesis_wcbxfzyt.yaml"
ARTEFACT = CONFIG / "artefacts" / "thesis_4ball.yaml"
TARGETS = CONFIG / "plans" / "targets" / "shift_start.yaml"
ERRORS = CONFIG / "errors" / "thesis_tableB2.yaml"
SIGMA = (0.66, 0.98, 0.44)


def stated_machine(tmp: Path, index_urad: float) -> Path:
    """The thesis machine file stating ``index_urad`` on B and C (nothing at 0)."""
    data = yaml.safe_load(MACHINE.read_text())
    if index_urad:
        data["rotary_repeatability_urad"] = {"B": index_urad, "C": index_urad}
    path = tmp / f"machine_{index_urad:g}.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def link_errors(plan, n: int, index_urad: float, seed0: int = 0) -> dict[str, np.ndarray]:
    """Per link the errors (estimate − truth, µrad / µm) of ``n`` simulated runs of ``plan``
    with B/C index scatter ``index_urad``, estimated with σ given and the value stated."""
    machine, mf = load_machine(MACHINE)
    art = load_artefact(ARTEFACT)
    text = generate(machine, mf, art, plan, "fanuc").text
    e = yaml.safe_load(ERRORS.read_text())
    e["indexing"] = {"repeatability_urad": {"B": index_urad, "C": index_urad}}
    errs = errors_from_dict(e)
    out: dict[str, list[float]] = {}
    stated = {"B": index_urad, "C": index_urad} if index_urad else None
    for i in range(n):
        seed = seed0 + i
        truth = TruthModel.build(machine, mf, art, errs, seed=seed)  # seeds the index draws
        res = run_sync(truth, text, "fanuc", seed=seed)
        if res.state != "done":
            raise RuntimeError(f"run {i} (seed {seed}): {res.state} {res.alarm}")
        c = rows_to_centres(res.rows, art, plan.stylus_radius_mm).centres
        c = c.subset(~np.isin(c.pose, plan.indices("validate")))  # held out, as the daemon
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            est = estimate(machine, art, c, None, sigma_um=SIGMA,
                           rotary_repeatability_urad=stated)
        for k, (v, _, _) in est.links_si().items():
            out.setdefault(k, []).append(v - float(truth.errors.links[k]))
    return {k: np.array(v) for k, v in out.items()}


def main(argv: list[str]) -> None:
    n = int(argv[0]) if argv else 30
    index = float(argv[1]) if len(argv) > 1 else 4.0
    machine, _ = load_machine(MACHINE)
    art = load_artefact(ARTEFACT)
    four = {"B": index, "C": index}
    with tempfile.TemporaryDirectory() as tmp:
        plans = {
            "optimised-stated": make_plan(stated_machine(Path(tmp), index), ARTEFACT, TARGETS,
                                          "fanuc").plan,
            "optimised-none": make_plan(stated_machine(Path(tmp), 0.0), ARTEFACT, TARGETS,
                                        "fanuc").plan,
            "shift_start_14poses": load_plan(CONFIG / "plans" / "shift_start_14poses.yaml")}
    only = argv[2:] or list(plans)
    print(f"thesis machine, B/C index scatter {index:g} µrad 1σ stated, N = {n} runs per plan")
    for name, plan in plans.items():
        if name not in only:
            continue
        links, _ = plan_links(machine, art, plan)
        u4, _ = predicted_u(machine, art, plan, links, SIGMA, index_urad=four)
        u0, _ = predicted_u(machine, art, plan, links, SIGMA)
        err = link_errors(plan, n, index)
        print(f"\n{name}: {len(plan.poses)} poses; "
              + ", ".join(f"B{p.b_deg:g} C{p.c_deg:g}" for p in plan.poses))
        print(f"{'link':6}{'u stated':>10}{'u none':>9}{'rms err':>9}{'rms/u st':>10}"
              f"{'rms/u none':>11}{'in 2u st':>9}{'in 2u none':>11}{'mean err':>10}")
        r4, r0, c4, c0 = [], [], [], []
        for k in links:
            e = err[k]
            rms = float(np.sqrt(np.mean(e ** 2)))
            r4.append(rms / u4[k])
            r0.append(rms / u0[k])
            c4.append(float(np.mean(np.abs(e) <= 2 * u4[k])))
            c0.append(float(np.mean(np.abs(e) <= 2 * u0[k])))
            print(f"{k:6}{u4[k]:10.3f}{u0[k]:9.3f}{rms:9.3f}{r4[-1]:10.2f}{r0[-1]:11.2f}"
                  f"{100 * c4[-1]:8.0f}%{100 * c0[-1]:10.0f}%{float(np.mean(e)):10.3f}")
        se = 1.0 / np.sqrt(2 * n)
        print(f"mean over links: rms/u stated {np.mean(r4):.3f} (range {min(r4):.2f}-"
              f"{max(r4):.2f}; se per link ≈ {se:.2f}), nothing stated {np.mean(r0):.3f} "
              f"({min(r0):.2f}-{max(r0):.2f}); within 2u stated {100 * np.mean(c4):.1f} %, "
              f"nothing stated {100 * np.mean(c0):.1f} %")


if __name__ == "__main__":
    main(sys.argv[1:])
