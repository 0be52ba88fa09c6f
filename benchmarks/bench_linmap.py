# ruff: noqa: E402  (BLAS threads are set before numpy is first imported)
"""The map of the linear axes on the simulator: Monte Carlo of prediction error and coverage.

Per seed a machine is drawn — the 18 motion errors of its linear axes random smooth (Legendre
degrees 1-4 over each axis' travel, max |e| uniform in 5-20 µm and 10-30 µrad), the three
squareness errors N(0, 20 µrad), the other links of the machine's errors file, ball setups
N(0, 200 µm) per placement, one probe setup N(0, 50 µm) for every placement (one stylus), 0.5 µm
touch noise, 5 µrad 1σ index scatter on both rotary axes, a little warm-up (1.5 µm per axis
from cold with τ = 40 min) — and each placement's program (the machine's map plan) is run on
the virtual controller (``simulators.offline``), its log fitted to centres as ``rumba map``
does, and the map estimated (``identification.linmap``). The artefact's calibrated distance is
the true one of that draw plus N(0, 0.5 µm) (a calibration certificate's uncertainty).

At ``HELD_OUT`` random points inside the covered box (rotary axes at zero) the predicted error,
under the map's rigid convention, is compared with the truth under the same convention (the best
rigid motion over the covered grid of both removed, i.e. of their difference): per seed the
RMS of the truth and of the difference (vector magnitudes), the share of components within
2u, and d/u. Writes one JSON line per seed and prints the table:

    nice -n 10 .venv/bin/python -m benchmarks.bench_linmap thesis 50 out=bench_linmap.jsonl
    nice -n 10 .venv/bin/python -m benchmarks.bench_linmap swivelhead 50
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # small dense problems: threads only contend (×7 slower)

import json
import sys
import time
import warnings
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import yaml

from contracts.setup_files import load_artefact, load_machine, load_plan
from daemon.analysis.touch_centres import rows_to_centres
from identification.kinematics import ChainState, frames, to_model
from identification.linmap.field import (
    MapModel,
    box_from_ranges,
    predict_field,
    raw_field,
    rigid_design,
)
from identification.linmap.fit import MapOptions, fit_map
from identification.linmap.problem import Placement
from programs.generate import generate
from simulators.errors_schema import errors_from_dict
from simulators.offline import run_sync
from simulators.truth import TruthModel

ROOT = Path(__file__).resolve().parent.parent
CONFIG = ROOT / "config"
HELD_OUT = 300
SQUARENESS_URAD = 20.0
INDEX_URAD = 5.0
WARMUP_UM, WARMUP_TAU_S = 1.5, 2400.0


@dataclass(frozen=True)
class Case:
    machine: str
    errors: str  # the machine's errors file: its links (squareness redrawn) and setup style
    placements: tuple[tuple[str, str], ...]  # (artefact, plan) per placement
    squareness: tuple[str, ...]


CASES = {
    "thesis": Case("thesis_wcbxfzyt.yaml", "thesis_tableB2.yaml",
                   (("thesis_4ball_scaled.yaml", "thesis_map_36poses.yaml"),
                    ("thesis_4ball_map2.yaml", "thesis_map_36poses.yaml")),
                   ("EB0Z", "EA0Y", "EC0Y")),
    "swivelhead": Case("swivelhead_wcfxyzbt.yaml", "swivelhead_wcfxyzbt.yaml",
                       (("vertical_4ball_scaled.yaml", "swivelhead_map_24poses.yaml"),
                        ("vertical_4ball_map2.yaml", "swivelhead_map_24poses.yaml")),
                       ("EC0Y", "EA0Z", "EB0Z")),
}


CLEAN = False  # ``clean``: no noise, no index scatter, no warm-up (the model's own floor)
NO_WARMUP = False  # ``nowarm``: the noise and index scatter without the warm-up


def draw_errors(case: Case, seed: int) -> dict:
    """The errors file of one draw (module docstring)."""
    rng = np.random.default_rng([seed, 38])
    e = yaml.safe_load((CONFIG / "errors" / case.errors).read_text())
    links = dict(e.get("links", {}))
    for name in case.squareness:
        links[name] = float(rng.normal(0.0, SQUARENESS_URAD))
    axes = {a: {"amplitude_um": float(WARMUP_UM * rng.choice([-1, 1])), "tau_s": WARMUP_TAU_S}
            for a in "XYZ"}
    if CLEAN:
        return {"machine": e.get("machine"), "seed": seed, "links": links,
                "setup": {"random_balls_std_um": 200.0,
                          "probe_um": [float(x) for x in rng.normal(0.0, 50.0, 3)]},
                "probe": {"stylus_diameter_mm": 6.0},
                "motion_errors": {"random_smooth": {"seed": seed, "translation_um": [5, 20],
                                                   "rotation_urad": [10, 30], "order": 4}}}
    return {"machine": e.get("machine"), "seed": seed, "links": links,
            "setup": {"random_balls_std_um": 200.0,
                      "probe_um": [float(x) for x in rng.normal(0.0, 50.0, 3)]},
            "probe": {"stylus_diameter_mm": 6.0, "touch_noise_um": 0.5},
            "indexing": {"repeatability_urad": {"B": INDEX_URAD, "C": INDEX_URAD}},
            "thermal": {"axes": {} if NO_WARMUP else axes},
            "motion_errors": {"random_smooth": {"seed": seed, "translation_um": [5, 20],
                                               "rotation_urad": [10, 30], "order": 4}}}


def true_field(truth: TruthModel, xyz: np.ndarray) -> np.ndarray:
    """(N, 3) mm: the true tool tip minus the nominal one in the workpiece frame, rotary 0."""
    m = truth.machine
    q = {a: xyz[:, i] for i, a in enumerate("XYZ")}
    q.update({r: np.zeros(len(xyz)) for r in m.rotary_axes})
    qm = to_model(m, q)

    def tip_w(state: ChainState) -> np.ndarray:
        f_w, f_t = frames(m, qm, state)
        t = f_t[:, :3, :3] @ np.asarray(m.tool_tip_mm, float) + f_t[:, :3, 3]
        return np.einsum("sji,sj->si", f_w[:, :3, :3], t - f_w[:, :3, 3])

    true_state = ChainState(links=truth.state.links, motion_errors=truth.state.motion_errors)
    return tip_w(true_state) - tip_w(ChainState())


def run_seed(case: Case, seed: int) -> dict:
    m, mf = load_machine(CONFIG / "machines" / case.machine)
    errs = errors_from_dict(draw_errors(case, seed))
    placements, machine_s, truth = [], 0.0, None
    for k, (art_name, plan_name) in enumerate(case.placements):
        art = load_artefact(CONFIG / "artefacts" / art_name)
        plan = load_plan(CONFIG / "plans" / plan_name)
        truth = TruthModel.build(m, mf, art, errs, seed=seed * 10 + k)
        if art.distances:  # the certificate: the true distance ± 0.5 µm
            w = truth.artefact.nominal_mm + truth.ball_setup_mm
            rng = np.random.default_rng([seed, k, 7])
            ids = art.ids
            art = replace(art, distances=tuple(
                replace(d, distance_mm=float(np.linalg.norm(w[ids.index(d.ball_a)]
                                                             - w[ids.index(d.ball_b)])
                                             + rng.normal(0.0, d.std_um * 1e-3)))
                for d in art.distances))
        text = generate(m, mf, art, plan, "fanuc").text
        res = run_sync(truth, text, "fanuc", seed=seed * 10 + k)
        if res.state != "done":
            raise RuntimeError(f"seed {seed} placement {k}: {res.state} {res.alarm}")
        machine_s += res.machine_time_s
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            data = rows_to_centres(res.rows, art, plan.stylus_radius_mm)
        placements.append(Placement(f"P{k + 1}", art, data.centres, data.points_mm,
                                    data.radius_nominal_mm))
    t0 = time.perf_counter()
    est = fit_map(m, placements, MapOptions(rotary_repeatability_urad=mf.rotary_repeatability_urad))
    fit_s = time.perf_counter() - t0
    n = est.layout.n_model
    model = MapModel(m, est.layout.links, est.basis, est.p[:n], est.cov[:n, :n],
                     box_from_ranges(m, est.basis.ranges_mm))
    rng = np.random.default_rng([seed, 99])
    pts = np.column_stack([rng.uniform(*model.box_mm[a], HELD_OUT) for a in "XYZ"])
    pred = predict_field(model, pts)
    grid = model.grid()
    _, _, pg = raw_field(model, grid)
    _, _, pp = raw_field(model, pts)
    centre = pg.mean(axis=0)
    fit = np.linalg.pinv(rigid_design(pg, centre).reshape(-1, 6))
    assert truth is not None
    et = true_field(truth, pts) - rigid_design(pp, centre) @ (fit @ true_field(truth, grid)
                                                              .reshape(-1))
    et_um = et * 1e3
    d = pred.error_um - et_um
    z = d / pred.u_um
    return {"seed": seed, "machine_time_s": machine_s, "fit_s": fit_s,
            "truth_rms_um": float(np.sqrt(np.mean(np.sum(et_um**2, axis=1)))),
            "diff_rms_um": float(np.sqrt(np.mean(np.sum(d**2, axis=1)))),
            "diff_max_um": float(np.max(np.linalg.norm(d, axis=1))),
            "cover2u": float(np.mean(np.abs(z) <= 2.0)), "z_mean": float(np.mean(z)),
            "z_sd": float(np.std(z)), "u_mean_um": float(np.mean(pred.u_um)),
            "degrees": est.order.degrees if est.order else None,
            "residual_rms_um": est.residual_rms_um, "box_mm": model.box_mm,
            "terms": est.basis.size, "links": len(est.layout.links)}


def table(rows: list[dict]) -> str:
    ok = [r["diff_rms_um"] <= max(0.25 * r["truth_rms_um"], 1.0) for r in rows]
    ratio = np.array([r["diff_rms_um"] / r["truth_rms_um"] for r in rows])
    cov = np.array([r["cover2u"] for r in rows])
    zm = np.array([r["z_mean"] for r in rows])
    se = float(zm.std(ddof=1) / np.sqrt(len(rows))) if len(rows) > 1 else 0.0
    lines = [f"N = {len(rows)} seeds, {HELD_OUT} held-out points each",
             f"machine time per map: {np.mean([r['machine_time_s'] for r in rows]) / 60:.1f} "
             "min (simulated)",
             f"truth RMS: median {np.median([r['truth_rms_um'] for r in rows]):.2f} µm "
             f"(min {min(r['truth_rms_um'] for r in rows):.2f})",
             f"difference RMS: median {np.median([r['diff_rms_um'] for r in rows]):.2f} µm, "
             f"max {max(r['diff_rms_um'] for r in rows):.2f}; ratio to truth RMS median "
             f"{np.median(ratio):.3f}, max {ratio.max():.3f}",
             f"seeds within max(25 % of truth RMS, 1 µm): {sum(ok)}/{len(rows)}",
             f"2u coverage of the components: {100 * cov.mean():.1f} % (seed min "
             f"{100 * cov.min():.1f} %)",
             f"bias: mean d/u {zm.mean():+.3f} ± {se:.3f} (se over seeds); sd(d/u) "
             f"{np.mean([r['z_sd'] for r in rows]):.2f}",
             f"fit time median {np.median([r['fit_s'] for r in rows]):.1f} s"]
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    name = argv[0] if argv else "thesis"
    n = int(argv[1]) if len(argv) > 1 else 5
    out = next((a.split("=", 1)[1] for a in argv if a.startswith("out=")), None)
    start = int(next((a.split("=", 1)[1] for a in argv if a.startswith("from=")), 0))
    global CLEAN
    CLEAN = "clean" in argv
    global NO_WARMUP
    NO_WARMUP = "nowarm" in argv
    rows = []
    if out and Path(out).exists():
        rows = [json.loads(x) for x in Path(out).read_text().splitlines() if x.strip()]
        rows = [r for r in rows if r.get("case") == name]
    done = {r["seed"] for r in rows}
    for seed in range(start, n):
        if seed in done:
            continue
        r = run_seed(CASES[name], seed) | {"case": name}
        rows.append(r)
        print(json.dumps({k: (round(v, 3) if isinstance(v, float) else v)
                          for k, v in r.items() if k != "box_mm"}), flush=True)
        if out:
            with open(out, "a", encoding="utf-8") as f:
                f.write(json.dumps(r) + "\n")
    print(table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
