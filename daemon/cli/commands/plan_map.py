"""``rumba plan --map``: the placements and poses of a map of the linear axes within a machine-time
budget (``programs.map_plan``), printed with what each placement adds, written as one plan file
per placement and the map-job file the daemon (``map_job``) and ``rumba map`` read."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import yaml

from contracts.setup_files import ConfigError, load_plan
from contracts.yaml_files import read_yaml
from programs.map_plan import PLAN_SETTINGS, MapPlan, MapPlanError, plan_map

SETTING_KEYS = ("stylus_diameter_mm", "stylus_length_mm", "stem_diameter_mm", "feeds",
                "standoff_mm", "overtravel_mm", "clearance_mm", "dwell_s")


def _error(msg: str) -> Exception:
    from daemon.cli.main import UserError

    return UserError(msg)


def parse_box(text: str | None) -> dict[str, tuple[float, float]] | None:
    if text is None:
        return None
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        v = []
    if len(v) != 6 or not all(abs(x) < 1e5 for x in v):
        raise _error(f"--box: expected X0,X1,Y0,Y1,Z0,Z1 (mm, six numbers), got {text!r}")
    return {a: (v[2 * i], v[2 * i + 1]) for i, a in enumerate("XYZ")}


def _settings(base: Path | None) -> dict:
    """The probing settings of ``--plan BASE`` (its poses ignored), or the shipped map plans'."""
    if base is None:
        return dict(PLAN_SETTINGS)
    load_plan(base)  # checked as a plan first: errors name the file and key
    data = read_yaml(base)
    return {k: data[k] for k in SETTING_KEYS if k in data}


def _out_paths(out: Path, n: int, force: bool) -> list[Path]:
    stem = out.name[:-5] if out.name.endswith(".yaml") else out.name
    paths = [out, *(out.with_name(f"{stem}-P{i + 1}.yaml") for i in range(n))]
    for p in paths:
        if p.is_symlink():
            raise _error(f"{p}: is a symbolic link; refusing to write through it")
        if p.exists() and not force:
            raise _error(f"{p}: exists; choose another --output or add --force")
    return paths


def _write(path: Path, text: str, force: bool) -> None:
    from daemon.cli.commands.plan import write_new

    write_new(path, text, force)


def _rel(target: Path, folder: Path) -> str:
    return os.path.relpath(target.resolve(), folder.resolve())


def write_job(mp: MapPlan, out: Path, name: str, force: bool) -> list[Path]:
    """The plan file of every placement and the map-job file naming them; the paths written."""
    paths = _out_paths(out, len(mp.steps), force)
    placements = []
    for i, (step, path) in enumerate(zip(mp.steps, paths[1:], strict=True)):
        c = step.candidate
        plan = {"name": f"{name}-P{i + 1}"[:32], **_plan_settings(c.plan),
                "poses": [{"b_deg": p.b_deg, "c_deg": p.c_deg} for p in c.plan.poses]}
        head = (f"# Map plan of placement P{i + 1} ({step.artefact.name}), written by rumba "
                f"plan --map: {len(c.plan.poses)} indexations ({c.grid[0]} tilts × "
                f"{c.grid[1]} turns), {c.touches} touches, {c.seconds / 60:.1f} min estimated\n")
        _write(path, head + yaml.safe_dump(plan, sort_keys=False), force)
        placements.append({"name": f"P{i + 1}", "plan": path.name,
                           "artefact": _rel(step.artefact_path, out.parent)})
    job = {"name": name[:32], "placements": placements}
    head = (f"# Map job written by rumba plan --map: {len(placements)} placements, "
            f"{mp.seconds / 60:.1f} min of machine time estimated (budget "
            f"{mp.budget_s / 60:g} min). daemon.yaml: map_job: <this file>\n")
    _write(out, head + yaml.safe_dump(job, sort_keys=False), force)
    return paths


def _plan_settings(plan: object) -> dict:
    d = plan.model_dump(mode="json")  # type: ignore[attr-defined]
    return {k: d[k] for k in SETTING_KEYS if d.get(k) is not None}


def render(mp: MapPlan) -> None:
    t = mp.target_mm
    print(f"{mp.machine.name}: map of " + ", ".join(
        f"{a} {lo:g}..{hi:g}" for a, (lo, hi) in t.items()) + " mm, budget "
        f"{mp.budget_s / 60:g} min")
    for i, s in enumerate(mp.steps):
        c = s.candidate
        print(f"P{i + 1} {s.artefact.name} ({s.artefact_path}): {len(c.plan.poses)} "
              f"indexations ({c.grid[0]} tilts × {c.grid[1]} turns), {c.touches} touches, "
              f"{c.seconds / 60:.1f} min")
        print("   covered so far: " + ", ".join(
            f"{a} {lo:.0f}..{hi:.0f} mm (+{s.added_mm[a]:.0f})"
            for a, (lo, hi) in s.covered_mm.items()))
        if s.new_terms:
            print(f"   observable from here: {len(s.new_terms)} map terms "
                  f"({', '.join(s.new_terms[:6])}{' …' if len(s.new_terms) > 6 else ''})")
        if s.better:
            ratios = sorted(b / a for b, a in s.better.values())
            print(f"   better determined: {len(s.better)} terms, their predicted u divided "
                  f"by {ratios[len(ratios) // 2]:.1f} (median; σ 1 µm per centre coordinate)")
        if not s.new_terms and not s.better:
            print("   adds stroke only: no term becomes observable or better determined")
    said = mp.steps[-1].observability.statement(mp.machine)
    whole = [k for k in said if "_P" not in k and k[:1] == "E" and len(k) == 3]
    links = [k for k in said if "_P" not in k and k not in whole]
    terms = [k for k in said if "_P" in k]
    print(f"total {mp.seconds / 60:.1f} min of machine time (estimate, "
          f"programs/cycletime.py); covered " + ", ".join(
              f"{a} {100 * f:.0f} %" for a, f in mp.coverage.items()) + " of the target")
    if whole:
        print(f"not observable with these placements, every degree: {', '.join(whole)} "
              "(rumba map names what holds each)")
    if terms or links:
        print(f"not observable: {len(terms)} more single terms ({', '.join(terms[:6])}"
              f"{' …' if len(terms) > 6 else ''})" + (f" and {', '.join(links)}" if links
                                                      else ""))
    for why in mp.refused:
        print(f"refused by the safety check: {why}")


def run_map_plan(args: argparse.Namespace) -> int:
    out = args.output or Path("map-job.yaml")
    _out_paths(out, 0, args.force)
    name = out.name[:-5] if out.name.endswith(".yaml") else out.name
    from contracts.setup_types import SAFE_NAME

    if not SAFE_NAME.fullmatch(name[:32]):
        raise _error(f"--output {out}: the file's name is the job's name: letters, digits, "
                     "'_', '.', '-'")
    try:
        mp = plan_map(args.machine, args.artefact, args.budget_min * 60, args.dialect,
                      parse_box(args.box), args.min_coverage, args.tilt_max_deg,
                      _settings(args.plan))
    except MapPlanError as e:
        raise _error(f"rumba plan --map: {e}") from None
    except ConfigError as e:
        raise _error(str(e)) from None
    render(mp)
    for p in write_job(mp, out, name, args.force):
        print(f"wrote {p}")
    return 0
