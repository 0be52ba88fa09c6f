"""The PDF's third page: the sections the HTML carries below the plots, and the approval block."""

# The PDF for filing carries what the HTML does — each figure with its
# definition, the link errors by ISO 230-1 code, plain name and the controller's own term, the
# setup errors, the validation on held-out poses, probe and ball health, the decision rule and
# a prepared / checked / approved block with date and signature lines. Text only, placed line
# after line from the top (no fixed bands, so nothing is left blank between sections).

from __future__ import annotations

from typing import Any

from daemon.analysis.result import Analysis

X_VALUE_IN = 3.4  # the value column of the link and setup tables (inches from the margin)


def _head(p: Any, title: str) -> None:
    p.y += 0.06
    p.line(title, size=10, weight="bold", gap=1.25)


def _row(p: Any, cells: list[tuple[float, str]], **kw: Any) -> None:
    for x, s in cells:
        p.text(p.margin + x, s, size=7.5, **kw)
    p.y += p.line_in


def page3(p: Any, analysis: Analysis, doc: dict[str, Any], audit: Any,
          prepared_by: str, date: str) -> None:
    """Everything below the plots of the HTML report, top to bottom on page ``p``."""
    _head(p, "Figures and their definitions")
    for f in doc.get("figures", []):
        v = "—" if f["value"] is None else f"{f['value']:.1f} {f['unit']}"
        p.wrapped(f"{f['label']}: {v} — {f['definition']}", width=130, indent="   ")
    _head(p, "Link errors")
    p.wrapped(doc.get("links_definition", ""), width=130, color="#444444")
    _row(p, [(0.0, "ISO 230-1 — name, controller term"), (X_VALUE_IN + 1.0, "value"),
             (X_VALUE_IN + 1.8, "u (k=1)"), (X_VALUE_IN + 2.5, "unit")], weight="bold")
    names = getattr(audit, "link_names", {}) or {}
    for n, v in sorted(analysis.links.items()):
        _row(p, [(0.0, names.get(n, n)), (X_VALUE_IN + 1.0, f"{v.value:+.2f}"),
                 (X_VALUE_IN + 1.8, f"{v.std or 0:.2f}"),
                 (X_VALUE_IN + 2.5, "µrad" if v.unit == "urad" else "µm")])
    p.line(f"Not observable: {', '.join(analysis.unobservable) or 'nothing'}.", color="#444444")
    _setup(p, analysis)
    val = analysis.validation
    if val is not None and val.rms_before_um is not None:
        _head(p, "Validation on held-out poses")
        p.line(f"Poses {', '.join(str(x) for x in val.poses)}: RMS {val.rms_before_um:.1f} → "
               f"{val.rms_after_um or 0:.1f} µm, max {val.max_before_um or 0:.1f} → "
               f"{val.max_after_um or 0:.1f} µm; explained "
               f"{100 * (val.explained_fraction or 0):.0f} %.")
    _health(p, analysis)
    comp = doc.get("compensation")
    if comp:
        _head(p, "Compensation verified by this run")
        # the addresses as the program wrote them (the controller's unit and sign)
        written = ", ".join(f"{w['address']} = {w['written']} (was {w['was']})"
                            for w in comp.get("writes") or ()) or ", ".join(
            f"{v['name']} ({v['address']}) {v['old']:.6f} → {v['new']:.6f} {v['unit']}"
            for v in comp["values"])
        p.wrapped(f"Journal #{comp['journal_row']}: written after run {comp['source_run']}, "
                  f"confirmed by {comp['confirmed_by']}; wrote: {written}", width=130)
    if getattr(audit, "decision_rule", None):
        _head(p, "Decision rule")
        p.wrapped(audit.decision_rule, width=130)
    _approval(p, prepared_by, date)


def _setup(p: Any, analysis: Analysis) -> None:
    st = analysis.setup
    if st is None:
        return
    _head(p, "Setup errors")
    _row(p, [(0.0, "item"), (1.2, "dx / µm"), (2.0, "dy / µm"), (2.8, "dz / µm"),
             (3.6, "u / µm")], weight="bold")
    items = [("probe", st.probe), *((f"ball {b}", v) for b, v in sorted(st.balls.items()))]
    for name, off in items:
        vals = [f"{x:+.1f}" if x is not None else "—" for x in off.value]
        u = max((x for x in off.std if x is not None), default=0.0)
        _row(p, [(0.0, name), *((1.2 + 0.8 * k, s) for k, s in enumerate(vals)),
                 (3.6, f"{u:.2f}")])


def _health(p: Any, analysis: Analysis) -> None:
    _head(p, "Probe and ball health")
    rad = max((abs(h.radius_dev_um or 0.0) for h in analysis.health), default=0.0)
    form = max((h.form_rms_um or 0.0 for h in analysis.health), default=0.0)
    p.line(f"Largest sphere-fit radius deviation {rad:.1f} µm, largest form residual "
           f"{form:.2f} µm.")
    stab = analysis.stability
    if stab is not None:
        p.line(f"Stability during the run: largest ball-centre shift between first and last "
               f"visit {stab.max_shift_um:.1f} µm (ball {stab.worst.ball}, pose "
               f"{stab.worst.pose}).")


def _approval(p: Any, prepared_by: str, date: str) -> None:
    _head(p, "Approval")
    _row(p, [(0.0, "role"), (1.3, "name"), (3.6, "date"), (4.9, "signature")], weight="bold")
    for k, role in enumerate(("Prepared by", "Checked by", "Approved by")):
        p.y += 0.12
        _row(p, [(0.0, role), (1.3, prepared_by if k == 0 else "_" * 28),
                 (3.6, date if k == 0 else "_" * 14), (4.9, "_" * 30)])
