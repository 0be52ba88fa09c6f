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
from identification.outliers import CENTRE_Z, MIN_SIZE_UM, SPHERE_Z, SUSPECT_Z, find_outliers

VERDICT = "measurement_outlier"


def exclude_outliers(machine: Machine, artefact: Artefact, data: TouchData,
                     hold_rows: np.ndarray, groups: Groups, stylus_radius_mm: float,
                     train: TouchData | None = None, keep: frozenset[int] = frozenset(),
                     drop: frozenset[int] = frozenset()
                     ) -> tuple[TouchData, np.ndarray, Groups, dict[str, Any]]:
    """Screen every ball visit; return the touches, hold-out flags and groups without the
    faulty visits, and the report parts ``outlier_test`` and ``outliers`` (each named by its
    log, pose, ball, repeat, touch and size). ``train``: the training log when a separate
    hold-out log was merged after it (``diagnose._merge`` shifts the hold-out's pose and
    repeat numbers past the training log's; they are shifted back to name a visit). ``keep``:
    visits (indices into ``groups``) kept in although the test names them (a pattern across
    visits explains them, ``visit_faults``); ``drop``: visits left out although it does not.
    Each outlier carries its ``index``; ``outlier_test.pole_suspect`` names the visit most
    displaced along its pole normal below the threshold (``visit_faults``), or is None."""
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
                         # the smallest chip this run names, by touch
                         "min_chip_um": min_chip_um(scr.radius_scale_um, scr.form_scale_um,
                                                    scr.centre_scale_um)},
        "outliers": []}
    def visit(k: int) -> dict[str, Any]:
        ho = bool(hold_rows[groups.touch_index[k, 0]])
        return {"index": int(k), "log": "holdout" if ho else "train",
                "pose": int(c.pose[k]) - (holdout_offsets[0] if ho else 0),
                "repeat": int(groups.repeat[k]) - (holdout_offsets[1] if ho else 0),
                "ball": artefact.ids[int(c.ball[k])], "b_deg": round(float(c.b_deg[k]), 4),
                "c_deg": round(float(c.c_deg[k]), 4)}

    flagged = {o.index for o in scr.outliers}
    z = np.where(np.isin(np.arange(len(c)), [*flagged, *drop]), -np.inf, scr.centre_z) \
        if scr.centre_z.size else np.zeros(0)
    best = int(np.argmax(z)) if z.size else -1
    parts["outlier_test"]["pole_suspect"] = None
    if best >= 0 and z[best] >= SUSPECT_Z and z[best] * scr.centre_scale_um >= MIN_SIZE_UM:
        parts["outlier_test"]["pole_suspect"] = visit(best) | {
            "touch": 5, "z": round(float(z[best]), 2),
            "size_um": round(float(z[best] * scr.centre_scale_um), 2)}
    out = [o for o in scr.outliers if o.index not in keep]
    if not out and not drop:
        return data, hold_rows, groups, parts
    drop_rows = np.zeros(len(data), bool)
    for k in drop:
        drop_rows[groups.touch_index[k]] = True
    for o in sorted(out, key=lambda o: float(c.t_s[o.index])):
        drop_rows[groups.touch_index[o.index]] = True
        parts["outliers"].append(visit(o.index) | {
            "touch": o.touch, "size_um": round(o.size_um, 3), "score": round(o.score, 2),
            "stage": o.stage})
    keep_rows = ~drop_rows
    kept = TouchData(**{f: getattr(data, f)[keep_rows] for f in TouchData.__dataclass_fields__})
    return kept, hold_rows[keep_rows], group_touches(kept, artefact, stylus_radius_mm), parts


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
