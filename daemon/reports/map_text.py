"""The words and numbers of the map report, one source for its HTML, PDF and plots: each motion
error's state (observable, partly, not observable and why), the figures table, the list of what
the data do not determine."""

from __future__ import annotations

from dataclasses import dataclass

from contracts.linear_map import Function, LinearMapFile

DIRECTION = {"X": "X", "Y": "Y", "Z": "Z", "A": "about X", "B": "about Y", "C": "about Z"}


def unit_text(unit: str) -> str:
    return "µrad" if unit == "urad" else "µm"


def short(f: Function) -> str:
    """The plain name of a motion error: ``straightness of X in Y``."""
    d = f.name[1]
    return {"positioning": f"positioning of {f.axis}",
            "straightness": f"straightness of {f.axis} in {d}",
            "angular": (f"roll of {f.axis}" if d in "ABC" and "XYZ"["ABC".index(d)] == f.axis
                        else f"tilt of {f.axis} {DIRECTION[d]}")}[f.kind]


def title(f: Function) -> str:
    """``EYX — straightness of X in Y``: the ISO 230-1 code and its plain name."""
    return f"{f.name} — {short(f)}"


@dataclass(frozen=True)
class FunctionState:
    """What the report may say of one function: ``observable`` (every kept degree determined),
    ``partly`` (some degrees held by something else: named), ``none`` (no term determined:
    never drawn as if known)."""

    name: str
    state: str  # "observable" | "partly" | "none"
    why: str  # words: what holds the missing part ("" when observable)
    max_abs: float | None  # largest |value| over the covered range (None: not observable)
    u_at_max: float | None
    unit: str


def function_state(doc: LinearMapFile, f: Function) -> FunctionState:
    """The state of ``f`` from the map's observability statement (a component named there, or
    a function without a determined term, is not observable; a named term is a part held)."""
    stmt = doc.observability.unobservable
    unit = unit_text(f.unit)
    if not f.terms or f.name in stmt:
        why = stmt.get(f.name) or next(iter(f.absorbed.values()), "") or (
            "no term of it is determined by these placements")
        return FunctionState(f.name, "none", why, None, None, unit)
    i = max(range(len(f.value)), key=lambda k: abs(f.value[k]))
    held = {**f.absorbed, **{k: v for k, v in stmt.items() if k.startswith(f.name + "_P")}}
    if not held:
        return FunctionState(f.name, "observable", "", abs(f.value[i]), f.u[i], unit)
    why = "; ".join(f"degree {t.split('_P')[1]} held by {w}" for t, w in sorted(held.items()))
    return FunctionState(f.name, "partly", why, abs(f.value[i]), f.u[i], unit)


def states(doc: LinearMapFile) -> dict[str, FunctionState]:
    return {f.name: function_state(doc, f) for f in doc.functions}


@dataclass(frozen=True)
class FigureRow:
    label: str
    value: str
    detail: str
    status: str  # PASS / WARN / FAIL, "" without a limit


def figure_rows(doc: LinearMapFile) -> list[FigureRow]:
    """The figures table: volumetric error max (± u, where, verdict against the limit) and RMS
    over the covered volume, as written in the map's JSON (``figures``)."""
    fig = doc.figures
    m = fig.volumetric_max_um
    at = ", ".join(f"{a} {v:.0f}" for a, v in zip("XYZ", m.at_mm or [], strict=False))
    limit = (f"limit: {m.limit}" + (f" ({m.source})" if m.source else "")) if m.limit else (
        "no limit given (--limit-um or --config): not judged")
    return [
        FigureRow("Volumetric error, max", f"{m.value_um:.2f} µm" + (
            f" ± {m.u_um:.2f} µm (u, k=1)" if m.u_um is not None else ""),
            (f"at {at} mm; " if at else "") + limit, m.status or ""),
        FigureRow("Volumetric error, RMS", f"{fig.volumetric_rms_um:.2f} µm",
                  f"over {fig.points} points: {fig.grid}", ""),
    ]


def box_text(doc: LinearMapFile) -> str:
    return ", ".join(f"{a.axis} {a.range_mm[0]:.1f} … {a.range_mm[1]:.1f} mm"
                     for a in doc.basis.axes)


def degrees_text(doc: LinearMapFile) -> str:
    """``X 2, Y 2, Z 2``: the Legendre degree of each axis' functions."""
    return ", ".join(f"{a.axis} {a.degree}" for a in doc.basis.axes)


def unobservable_lines(doc: LinearMapFile) -> list[str]:
    """What the data do not determine, in words: the scale, whole functions, single degrees of
    a function, links (the daily check's statement), then the range the map holds."""
    obs = doc.observability
    st = states(doc)
    out = []
    if not obs.scale_observable:
        out.append("Isotropic scale of the linear axes: " + obs.unobservable.get(
            "isotropic_scale", "no calibrated distance between two balls"))
    gone: dict[str, list[str]] = {}  # one line per reason: EAY, EBY, ECY share theirs
    for s in st.values():
        if s.state == "none":
            gone.setdefault(s.why.removeprefix(s.why.split(":")[0] + ": ")
                            if s.why.startswith("every degree") else s.why, []).append(s.name)
    for why, names in gone.items():
        out.append(f"{', '.join(names)} {'is' if len(names) == 1 else 'are'} not observable: "
                   f"{why}")
    for s in st.values():
        if s.state == "partly":
            out.append(f"{s.name}: {s.why}")
    links = [(k, v) for k, v in obs.unobservable.items()  # not the scale, a function, a term
             if k != "isotropic_scale" and "_P" not in k and k not in st]
    if links:
        out.append("Link errors absorbed: " + "; ".join(f"{k} by {v}" for k, v in links))
    out.append(f"Outside the covered box ({box_text(doc)}) nothing is known: the map refuses "
               "to predict there.")
    return out
