"""Gross faults of single ball visits in a gap diagnosis: found by the run's outlier test
(``identification.outliers``), left out before the floor, the twin and the attribution, and
reported as their own verdict — a chip on one ball is neither the machine nor the twin's gap,
and one such visit would otherwise inflate the noise floor until the real gap reads ``none``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from identification.gap.chip_floor import min_chip_um
from identification.gap.data import Groups, TouchData, group_touches
from identification.kinematics import Machine
from identification.model import Artefact
from identification.outliers import CENTRE_Z, MIN_SIZE_UM, SPHERE_Z, find_outliers

VERDICT = "measurement_outlier"


def exclude_outliers(machine: Machine, artefact: Artefact, data: TouchData,
                     hold_rows: np.ndarray, groups: Groups, stylus_radius_mm: float,
                     train: TouchData | None = None
                     ) -> tuple[TouchData, np.ndarray, Groups, dict[str, Any]]:
    """Screen every ball visit; return the touches, hold-out flags and groups without the
    faulty visits, and the report parts ``outlier_test`` and ``outliers`` (each named by its
    log, pose, ball, repeat, touch and size). ``train``: the training log when a separate
    hold-out log was merged after it (``diagnose._merge`` shifts the hold-out's pose and
    repeat numbers past the training log's; they are shifted back to name a visit)."""
    holdout_offsets = (0, 0) if not train else (int(train.pose.max()) + 1,
                                                 int(train.repeat.max()) + 1)
    c = groups.centres
    r_nom = np.array([artefact.balls[b].diameter_mm / 2 for b in c.ball]) + stylus_radius_mm
    scr = find_outliers(machine, artefact, c, data.xyz_mm[groups.touch_index], r_nom,
                        groups.repeat)
    parts: dict[str, Any] = {
        "outlier_test": {"visits": scr.visits, "sphere_z": SPHERE_Z, "centre_z": CENTRE_Z,
                         "min_size_um": MIN_SIZE_UM,
                         "radius_scale_um": _r(scr.radius_scale_um),
                         "form_scale_um": _r(scr.form_scale_um),
                         "centre_scale_um": _r(scr.centre_scale_um), "note": scr.note,
                         # issue 21: the smallest chip this run names, by touch
                         "min_chip_um": min_chip_um(scr.radius_scale_um, scr.form_scale_um,
                                                    scr.centre_scale_um)},
        "outliers": []}
    if not scr.outliers:
        return data, hold_rows, groups, parts
    drop = np.zeros(len(data), bool)
    for o in sorted(scr.outliers, key=lambda o: float(c.t_s[o.index])):
        rows = groups.touch_index[o.index]
        drop[rows] = True
        ho = bool(hold_rows[rows[0]])
        parts["outliers"].append({
            "log": "holdout" if ho else "train",
            "pose": int(c.pose[o.index]) - (holdout_offsets[0] if ho else 0),
            "repeat": int(groups.repeat[o.index]) - (holdout_offsets[1] if ho else 0),
            "ball": artefact.ids[int(c.ball[o.index])],
            "b_deg": round(float(c.b_deg[o.index]), 4),
            "c_deg": round(float(c.c_deg[o.index]), 4), "touch": o.touch,
            "size_um": round(o.size_um, 3), "score": round(o.score, 2), "stage": o.stage})
    keep = ~drop
    kept = TouchData(**{f: getattr(data, f)[keep] for f in TouchData.__dataclass_fields__})
    return kept, hold_rows[keep], group_touches(kept, artefact, stylus_radius_mm), parts


def name(o: dict[str, Any]) -> str:
    """'ball B2 pose 7 touch 2 (+10.3 µm)', with the repeat and the log when they matter."""
    rep = f" repeat {o['repeat']}" if o["repeat"] else ""
    log = " of the hold-out log" if o["log"] == "holdout" else ""
    return f"ball {o['ball']} pose {o['pose']}{rep}{log} touch {o['touch']} " \
           f"({o['size_um']:+.1f} µm)"


def outlier_verdict(rep: dict[str, Any], parts: dict[str, Any]) -> dict[str, Any]:
    """The report with the test's parts; with faulty visits the verdict is
    ``measurement_outlier`` naming them, and what the diagnosis finds without them is kept
    under ``verdict.without_outliers``."""
    rep.update(parts)
    found = parts["outliers"]
    if found:
        v = rep["verdict"]
        without = {"effect": v["effect"], "axis": v["axis"], "message": v["message"]}
        axis = f":{v['axis']}" if v["axis"] else ""
        rep["verdict"] = {**v, "effect": VERDICT, "axis": None, "without_outliers": without,
                          "message": (f"{len(found)} ball visit(s) with one touch off the "
                                      f"sphere the rest of the run predicts — "
                                      f"{'; '.join(name(o) for o in found)}: a chip, dirt, "
                                      f"coolant or a bad trigger, not the machine; left out, "
                                      f"the rest reads {v['effect']}{axis} "
                                      f"({v['message']})")}
    return rep


def _r(x: float | None) -> float | None:
    return None if x is None else round(float(x), 4)
