"""The run's temperature channels as the report prints them: the audit row, the
PDF line and the HTML table's rows, from the analysis JSON's ``temperatures`` summary."""

from __future__ import annotations

from typing import Any

from contracts.temperatures import channel_text as contract_channel_text
from daemon.analysis.result import Analysis


def _c(v: float | None) -> str:
    return "—" if v is None else f"{v:.1f}"


def channel_text(name: str, t: dict[str, Any]) -> str:
    """"spindle 20.5 → 24.1 °C (+3.6 °C)", or why it was not read: the one text of every view
    (contracts.temperatures.channel_text, which the fleet page prints too)."""
    if not t.get("errors") and t.get("first_c", t.get("start_c")) is None:
        t = {**t, "errors": ["no reading"]}
    return contract_channel_text(name, t)


def temperature_lines(analysis: Analysis) -> list[str]:
    """One line per channel (the HMI's verdict card, the fleet page)."""
    return [channel_text(n, t) for n, t in (analysis.temperatures or {}).items()]


def audit_text(analysis: Analysis) -> str | None:
    """The audit row: each channel at start → end, then where the values came from."""
    temps = analysis.temperatures
    if not temps:
        return None
    return ("; ".join(channel_text(n, t) for n, t in temps.items())
            + " — from " + "; ".join(t.get("source", n) for n, t in temps.items()))


def table_rows(analysis: Analysis) -> list[dict[str, str]]:
    """One HTML row per channel: start, end, change, range and the value at each pose."""
    rows = []
    for name, t in (analysis.temperatures or {}).items():
        change = t.get("change_c")
        rows.append({
            "name": name, "source": str(t.get("source", "")), "start": _c(t.get("start_c")),
            "end": _c(t.get("end_c")),
            "change": "—" if change is None else f"{change:+.2f}" + (
                f" ({t['change_over']})" if t.get("change_over") not in (None, "start → end")
                else ""),
            "range": f"{_c(t.get('min_c'))} … {_c(t.get('max_c'))}",
            "per_pose": ", ".join(f"{p['pose']}: {p['value_c']:.1f}" + (
                f" (re-probe {p['reprobe_round']})" if p.get("reprobe_round") else "")
                for p in t.get("per_pose", [])),
            "unread": (f"{t['unread']} of {t['readings']} readings failed: "
                       + "; ".join(t.get("errors", []))) if t.get("unread") else ""})
    return rows
