"""Measured for ``bench_gap.py --faults``: pole chips and creeping balls."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from contracts.setup_files import load_artefact, load_machine, load_plan
from identification.effects import make_effect
from identification.gap import diagnose
from identification.gap.data import group_touches
from identification.gap.outlier_visits import exclude_outliers
from identification.gap.simlog import Truth, simulate
from identification.kinematics import Machine
from identification.model import Artefact

CONFIG = Path(__file__).resolve().parents[1] / "config"
TABLE_B2 = {"EB0Z": -12e-6, "EA0Y": -24e-6, "EC0Y": 17e-6, "EC0B": -23e-6, "EA0B": 2e-6,
            "EA0C": -19e-6, "EB0C": 26e-6, "EX0C": -0.106}
STYLUS_R = 3.0


def _setup() -> tuple[Machine, Artefact, list[tuple[float, float]]]:
    machine, _ = load_machine(CONFIG / "machines/thesis_wcbxfzyt.yaml")
    artefact = load_artefact(CONFIG / "artefacts/thesis_4ball.yaml")
    plan = load_plan(CONFIG / "plans/thesis_annexB_14poses.yaml")
    return machine, artefact, [(p.b_deg, p.c_deg) for p in plan.poses]


def _truth(artefact: Artefact, seed: int, scatter_urad: float) -> Truth:
    rng = np.random.default_rng(seed)
    t = Truth(dict(TABLE_B2), rng.normal(0, 0.2, (len(artefact.balls), 3)),
              rng.normal(0, 0.05, 3))
    if scatter_urad:
        t.index_std_urad = {"B": scatter_urad, "C": scatter_urad}
    return t


def _chip(setup, seed: int, size_um: float, touch: int | None, scatter_urad: float,
          noise_um: float = 0.6):
    """A run with one chip (``touch`` None: a random equator touch 1-4) and where it is."""
    machine, artefact, poses = setup
    rng = np.random.default_rng(seed + 555)
    data = simulate(machine, artefact, poses, _truth(artefact, seed, scatter_urad), STYLUS_R,
                    noise_um, seed=seed + 7919)
    pose, ball = int(rng.integers(len(poses))), int(rng.integers(len(artefact.balls)))
    touch = touch or int(rng.integers(1, 5))
    k = np.flatnonzero((data.pose == pose) & (data.ball == ball) & (data.touch == touch))[0]
    data.xyz_mm[k] -= size_um * 1e-3 * data.direction[k]
    return data, (pose, artefact.ids[ball], touch)


def detect(first: int, n: int) -> None:
    setup = _setup()
    machine, artefact, _ = setup
    for scatter in (0.0, 5.0):
        for where in ("pole", "equator"):
            for size in (8.0, 10.0, 15.0):
                named, stated, missed_above = 0, [], 0
                for s in range(first, first + n):
                    data, at = _chip(setup, s, size, 5 if where == "pole" else None, scatter)
                    g = group_touches(data, artefact, STYLUS_R)
                    parts = exclude_outliers(machine, artefact, data,
                                             np.zeros(len(data), bool), g, STYLUS_R)[3]
                    got = [(o["pose"], o["ball"], o["touch"]) for o in parts["outliers"]]
                    hit = got == [at]
                    floor = parts["outlier_test"]["min_chip_um"][where]
                    named += hit
                    stated.append(floor)
                    missed_above += (not hit) and size >= floor
                st = np.array(stated)
                print(json.dumps({"scatter_urad": scatter, "where": where, "size_um": size,
                                  "seeds": [first, first + n], "named": named,
                                  "stated_min_median": round(float(np.median(st)), 2),
                                  "stated_min_range": [float(st.min()), float(st.max())],
                                  "missed_at_or_above_stated": int(missed_above)}), flush=True)


def pole(first: int, n: int) -> None:
    setup = _setup()
    machine, artefact, _ = setup
    for s in range(first, first + n):
        data, at = _chip(setup, s, 10.0, 5, 5.0)
        rep = diagnose(machine, artefact, data, STYLUS_R)
        v = rep["verdict"]
        where = rep.get("pole_defect") or {}
        print(json.dumps({"seed": s, "verdict": v["effect"], "at": at,
                          "outliers": [(o["pose"], o["ball"], o["touch"])
                                       for o in rep["outliers"]],
                          "pole_defect_at": [where.get("pose"), where.get("ball")],
                          "pole_defect_um": where.get("size_um"),
                          "stated_min_pole": rep["outlier_test"]["min_chip_um"]["pole"]}),
              flush=True)


def creep(first: int, n: int) -> None:
    machine, artefact, poses = _setup()
    for s in range(first, first + n):
        rng = np.random.default_rng(s + 999)
        ball, size, sigma = int(rng.integers(4)), rng.uniform(5, 20), rng.uniform(5, 10)
        v = rng.normal(size=3)
        truth = _truth(artefact, s, sigma)
        span_h = np.ptp(simulate(machine, artefact, poses, truth, STYLUS_R, 0.5,
                                 seed=s + 7919).t_s) / 3600
        rate = v / np.linalg.norm(v) * size / span_h
        truth.effects = [(make_effect("artefact_instability", artefact.ids[ball], machine,
                                      ball_index=ball), rate)]
        rep = diagnose(machine, artefact, simulate(machine, artefact, poses, truth, STYLUS_R,
                                                   0.5, seed=s + 7919), STYLUS_R)
        got = rep.get("ball_creep") or {}
        est = np.array(got.get("vector_um_per_h", [np.nan] * 3))
        print(json.dumps({"seed": s, "ball": artefact.ids[ball], "size_um": round(size, 2),
                          "sigma_urad": round(sigma, 2), "verdict": rep["verdict"]["effect"],
                          "axis": rep["verdict"]["axis"],
                          "rate_err_um_h": round(float(np.linalg.norm(est - rate)), 3),
                          "rate_um_h": round(float(np.linalg.norm(rate)), 3),
                          "alike": got.get("indistinguishable_from")}), flush=True)


def run_faults(what: str, first: int, n: int) -> int:
    """Print one JSON line per row (detect) or per seed (pole, creep): sum them by hand."""
    {"detect": detect, "pole": pole, "creep": creep}[what](first, n)
    return 0
