"""``rumba history --machine M --against-temperature CHANNEL --link EX0C [--plot PNG]``: a link
error against a recorded temperature over the machine's runs, with r and the slope ± u
(daemon/analysis/temperature_trend.py), as a table and optionally a scatter plot."""

from __future__ import annotations

import argparse
from pathlib import Path

from daemon.analysis.temperature_trend import TempFit, TempPoint, fit, points
from daemon.cli.main import UserError
from daemon.config import DaemonConfig
from daemon.store.journal import Store


def cmd_against_temperature(cfg: DaemonConfig, store: Store, args: argparse.Namespace) -> int:
    channel, link = args.against_temperature, args.link
    if args.machine is None or link is None:
        raise UserError("--against-temperature needs --machine and --link (e.g. --link EX0C)")
    setup = cfg.machines[args.machine]
    names = [ch.name for ch in setup.temperatures]
    if channel not in names:
        raise UserError(f"{args.config}: machine {args.machine} has no temperature channel "
                        f"{channel!r} (configured: {', '.join(names) or 'none'})")
    if link not in setup.machine.location_error_names():
        raise UserError(f"--link {link}: not a location error of {args.machine} (known: "
                        f"{', '.join(sorted(setup.machine.location_error_names()))})")
    pts, unit = points(store.trend(args.machine, args.limit), link, channel)
    f = fit(pts, unit or ("µrad" if link[1] in "ABC" else "µm"))
    for p in pts:
        u = f" ± {p.std:.2f}" if p.std is not None else ""
        print(f"{p.run_id}  {channel} {p.temperature_c:6.2f} °C  {link} {p.value:+8.2f}{u} "
              f"{unit}")
    print(f.text(link, channel))
    if args.plot:
        plot(Path(args.plot), pts, f, link, channel, unit)
        print(f"wrote {args.plot}")
    return 0


def plot(path: Path, pts: list[TempPoint], f: TempFit, link: str, channel: str,
         unit: str) -> None:
    """Scatter of the runs (error bars: each run's u) with the fitted line, written to ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.0, 4.0))
    ax = fig.add_subplot()
    xs = [p.temperature_c for p in pts]
    ax.errorbar(xs, [p.value for p in pts], yerr=[p.std or 0.0 for p in pts], fmt="o",
                capsize=3)
    if f.slope is not None and xs:
        mt = sum(xs) / len(xs)
        mv = sum(p.value for p in pts) / len(pts)
        lo, hi = min(xs), max(xs)
        ax.plot([lo, hi], [mv + f.slope * (lo - mt), mv + f.slope * (hi - mt)], "-")
    ax.set_xlabel(f"{channel}, mean over the run (°C)")
    ax.set_ylabel(f"{link} ({unit})")
    ax.set_title(f.text(link, channel), fontsize=8)
    fig.savefig(path, dpi=100)
