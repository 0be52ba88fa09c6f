"""What ``rumba plan`` writes and compares: the chosen poses as a normal plan (the schema of
config/plans/*, loaded by ``contracts.setup_files``), its YAML text, and the predicted link
uncertainties of any plan as the daemon runs it (estimate-role poses + the drift revisit)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from contracts.setup_files import Plan, plan_from_dict
from identification.kinematics import Machine
from identification.model import Artefact
from programs.design import build_design, drift_u_worst, link_u, max_links
from programs.optimise import Chosen


def estimate_visits(plan: Plan) -> list[tuple[float, float]]:
    """The poses the estimate uses, in run order, once per visit: every repeat of the
    estimate-role poses and the drift-check revisit of the first pose (METHOD.md §3)."""
    est = [(p.b_deg, p.c_deg) for p in plan.poses if p.role == "estimate"]
    out = est * plan.repeats
    if plan.drift_check and plan.poses[0].role == "estimate":
        out.append((plan.poses[0].b_deg, plan.poses[0].c_deg))
    return out


def plan_links(machine: Machine, artefact: Artefact, plan: Plan
               ) -> tuple[tuple[str, ...], dict[str, str]]:
    """The link set the estimator identifies from this plan (and what absorbs the rest)."""
    return max_links(machine, artefact, estimate_visits(plan))


def predicted_u(machine: Machine, artefact: Artefact, plan: Plan, links: Sequence[str],
                sigma_um: Sequence[float], times_h: Sequence[float] | None = None,
                index_urad: Mapping[str, float] | None = None
                ) -> tuple[dict[str, float], dict[str, float] | None]:
    """Standard uncertainty per link (µrad / µm) of ``plan`` as the daemon estimates it; with
    the visit times (hours, one per estimate visit) also with a drift estimated (the worst of
    a linear drift and a warm-up of τ 10-60 min, ``drift_u_worst``); with ``index_urad``
    (the machine file's stated rotary repeatability) under that index scatter."""
    visits = estimate_visits(plan)
    uniq = sorted(set(visits))
    d = build_design(machine, artefact, uniq, links, sigma_um, index_urad)
    counts = np.zeros(len(uniq))
    for v in visits:
        counts[uniq.index(v)] += 1
    u = link_u(d, d.info_of(counts), d.meat_of(counts))
    du = None
    if times_h is not None:
        du_arr = drift_u_worst(d, [uniq.index(v) for v in visits], times_h)
        du = {k: float(x) for k, x in zip(links, du_arr, strict=True)}
    return {k: float(x) for k, x in zip(links, u, strict=True)}, du


def to_plan_dict(chosen: Chosen, probing: Plan, name: str) -> dict[str, Any]:
    """The plan file's content: ``probing``'s stylus, feeds, standoff … and the chosen poses,
    the first probed again at the end (drift check)."""
    feeds = {"probe_mm_min": probing.feeds.probe_mm_min,
             "approach_mm_min": probing.feeds.approach_mm_min}
    if probing.feeds.fast_probe_mm_min is not None:
        feeds["fast_probe_mm_min"] = probing.feeds.fast_probe_mm_min
    out: dict[str, Any] = {"name": name, "stylus_diameter_mm": probing.stylus_diameter_mm,
                           "stylus_length_mm": probing.stylus_length_mm}
    if probing.stem_diameter_mm is not None:
        out["stem_diameter_mm"] = probing.stem_diameter_mm
    out["poses"] = [({"b_deg": b, "c_deg": c} if role == "estimate" else
                     {"b_deg": b, "c_deg": c, "role": role})
                    for (b, c), role in zip(chosen.poses, chosen.roles, strict=True)]
    out.update({"drift_check": True, "feeds": feeds, "standoff_mm": probing.standoff_mm,
                "overtravel_mm": probing.overtravel_mm, "clearance_mm": probing.clearance_mm,
                "dwell_s": probing.dwell_s})
    return out


def to_plan(chosen: Chosen, probing: Plan, name: str) -> Plan:
    """The chosen plan through the normal loader (what every other command will read)."""
    return plan_from_dict(to_plan_dict(chosen, probing, name), f"<plan {name}>")


def _num(v: float) -> str:
    return f"{v:g}" if float(v).is_integer() or abs(v) >= 1e-3 else f"{v:.6f}"


def plan_yaml(data: dict[str, Any], header: Sequence[str]) -> str:
    """The plan file text: ``header`` as comments, one pose per line."""
    lines = [f"# {h}" if h else "#" for h in header]
    lines += [f"name: {data['name']}", f"stylus_diameter_mm: {_num(data['stylus_diameter_mm'])}",
              f"stylus_length_mm: {_num(data['stylus_length_mm'])}"]
    if "stem_diameter_mm" in data:
        lines.append(f"stem_diameter_mm: {_num(data['stem_diameter_mm'])}")
    lines.append("poses:")
    for p in data["poses"]:
        role = f", role: {p['role']}" if "role" in p else ""
        lines.append(f"  - {{b_deg: {_num(p['b_deg'])}, c_deg: {_num(p['c_deg'])}{role}}}")
    lines.append(f"drift_check: {'true' if data['drift_check'] else 'false'}")
    lines.append("feeds: {" + ", ".join(f"{k}: {_num(v)}" for k, v in data["feeds"].items())
                 + "}")
    for k in ("standoff_mm", "overtravel_mm", "clearance_mm", "dwell_s"):
        lines.append(f"{k}: {_num(data[k])}")
    return "\n".join(lines) + "\n"
