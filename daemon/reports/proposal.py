"""A compensation proposal as the page, the CLI and the review document show it: the changes
with Δ and U, the listing of what a confirmation writes (address by address, as written), the
links, the figures, the refusals, and the review document (JSON, never a program)."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

from daemon.analysis.figures import figures_json
from daemon.compensation.listing import fingerprint, listing_json
from daemon.compensation.propose import Proposal, unit_of
from daemon.safepath import contained_path
from identification.worth import plain

STATE_TEXT = {
    "proposed": "proposed: nothing is written to the controller and no program exists until "
                "a person confirms it",
    "nothing": "nothing to propose",
    "refused": "refused",
}
"""What each state of a proposal means, one line, the same on every surface."""


def to_um(kind_or_link: str, model_value: float) -> tuple[float, str]:
    """A model value (mm or rad) in µm or µrad: by the kind of a controller value (pivot /
    orientation) or the ISO name of a link (EA0B: rotation)."""
    rot = kind_or_link == "orientation" or (kind_or_link[:1] == "E" and kind_or_link[1:2]
                                            in ("A", "B", "C"))
    return (model_value * 1e6, "µrad") if rot else (model_value * 1e3, "µm")


def state_of(p: Proposal) -> str:
    """``proposed`` (a confirmation may write it), ``refused`` or ``nothing``."""
    if p.refusals:
        return "refused"
    return "proposed" if p.values and p.program is not None else "nothing"


def why_nothing(p: Proposal) -> str:
    """Why a proposal offers nothing to confirm, one sentence ("" when it does)."""
    state = state_of(p)
    if state == "refused":
        return "refused: " + "; ".join(p.refusals)
    if state == "nothing":
        if p.not_worth:
            return f"nothing worth writing: {p.not_worth}"
        return "nothing to change: every value is skipped (see each value's reason)"
    return ""


def proposal_dict(p: Proposal) -> dict[str, Any]:
    """The proposal for the page and the review document: values (Δ and U in µm / µrad, the
    worth rule's effect), the listing of the program a confirmation writes, links,
    distortion (µm), the state and why."""
    accepted = {v.name: v for v in p.values}
    passed = {ch.name for ch in p.guard.proposed} | set(accepted)
    values = []
    for ch in p.plan.changes:
        sp = p.spec.param(ch.name)
        v = accepted.get(ch.name)
        delta, unit = to_um(ch.kind, ch.delta)
        u = to_um(ch.kind, ch.u_expanded)[0]
        effect = p.plan.effect_um(ch.name)
        if v is not None:
            status, why = "apply", ""
        elif p.refusals and ch.name in passed:
            status, why = "refused", "the proposal is refused (see the reasons)"
        else:
            status, why = "skipped", p.skipped.get(ch.name, "not applied")
        values.append({"name": ch.name, "address": sp.address, "kind": ch.kind,
                       "old": v.old if v else p.current.get(ch.name),
                       "new": v.new if v else None, "unit": v.unit if v else unit_of(ch.kind)[0],
                       "delta": delta, "u": u, "delta_unit": unit, "status": status,
                       "delta_text": f"{plain(delta, 2, sign=True)} {unit}",
                       "u_text": f"{plain(u, 2)} {unit}",
                       "effect_um": effect, "reason": why})
    links = []
    for name, ident in p.plan.links_identified.items():
        value, unit = to_um(name, ident)  # rounded as the analysis JSON: the report's figure
        links.append({"name": name, "unit": unit, "identified": round(value, 4),
                      "compensable": to_um(name, p.plan.links_compensable[name])[0],
                      "residual": to_um(name, p.plan.links_residual[name])[0]})
    after = p.guard.after_um or p.plan.distortion_after_um
    dist = {k: {"rms": float(v[0]), "max": float(v[1])} for k, v in (
        ("before", p.plan.distortion_before_um), ("after", after))}
    listing = p.program.listing if p.program is not None else []
    state = state_of(p)
    return {"family": p.spec.family, "coverage_k": p.coverage_k, "values": values,
            "writes": listing_json(listing),
            "listing_fingerprint": fingerprint(p.spec.family, p.run_id, listing)
            if listing else None,
            "program_name": p.program.filename if p.program is not None else None,
            "links": links, "distortion_um": dist, "figures": figures_json(p.figures()),
            "links_from": p.links_from, "links_text": p.links_text(),
            "refusals": list(p.refusals), "state": state, "state_text": STATE_TEXT[state],
            "why": why_nothing(p), "min_effect_um": p.spec.min_effect_um,
            "applicable": state == "proposed"}


def review_document(p: Proposal, machine: str, confirm_with: str) -> dict[str, Any]:
    """The review document of a proposal: what a person checks before confirming; it holds
    no program (``writes`` lists the lines the program will hold once confirmed)."""
    return {"document": "rumba compensation proposal — a review document, not a program",
            "machine": machine, "run_id": p.run_id, "created_at": time.time(),
            "nothing_written": "No program exists and nothing was written to the controller: "
                               "the program is written only when a person confirms "
                               f"({confirm_with}, or Confirm on the operator page).",
            **proposal_dict(p)}


def write_review(reports_dir: Path, doc: dict[str, Any]) -> Path:
    """``proposal-<machine>-<run>.json`` in ``reports_dir`` (kept inside it)."""
    reports_dir.mkdir(parents=True, exist_ok=True)
    path = contained_path(reports_dir, f"proposal-{doc['machine']}-{doc['run_id']}.json")
    path.write_text(json.dumps(doc, indent=1, ensure_ascii=False) + "\n", encoding="utf-8")
    return path


__all__ = ["STATE_TEXT", "proposal_dict", "review_document", "state_of", "to_um",
           "why_nothing", "write_review"]
