"""Clearance of the tool bodies (probe body, spindle nose, head housing: ``tool.bodies`` of the
machine file) swept along the stylus tip's segments against balls, rods, table, boxes.

A body is a cylinder of radius R about the spindle axis from ``from_mm`` to ``to_mm`` above the
tip. At a fixed rotary pose it translates rigidly with the tip, so over a tip segment pa → pb its
axis sweeps the parallelogram ``pa + u·from + s·(pb − pa) + t·u·(to − from)`` (s, t in [0, 1]):
the swept body is everything within R of it. A ball (sphere) is clear when its centre is farther
than R + ball radius + standoff from that parallelogram; a rod (a segment) likewise with the rod
radius (``programs.clearance.point_par``, ``seg_par``). The table disc: the lowest point of a
cylinder with unit axis u is its lower end minus R·√(1 − u_z²); over the sweep it is lowest at
one end of the segment. Boxes: the body's axis at both segment ends and the path of its lower end,
each grown by R (a slab test, conservative at the box's corners).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from programs.clearance import TOL_MM, point_par, seg_box, seg_par
from programs.model import Program, ball_positions


def body_slack(prog: Program, pa: np.ndarray, pb: np.ndarray, stem: np.ndarray
               ) -> tuple[np.ndarray, Callable[[int], str]]:
    """Slack (mm, < 0 = violation) of every tool body over tip segments pa → pb (workpiece
    frame, (N, 3)) with unit spindle directions ``stem`` (N, 3), and the reason for segment j's
    tightest body. All inf when the machine file declares no bodies."""
    n = len(pa)
    bodies = prog.machine_file.tool.bodies
    if not bodies or n == 0:
        return np.full(n, np.inf), lambda j: ""
    art, standoff = prog.artefact, prog.standoff_mm
    balls_w = ball_positions(art, prog.targets)
    t = prog.machine_file.table
    rows: list[np.ndarray] = []
    why: list[tuple[str, float]] = []  # reason template, slack → gap offset
    e1 = pb - pa
    for body in bodies:
        p0 = pa + stem * body.from_mm
        e2 = stem * (body.to_mm - body.from_mm)
        r = body.radius_mm
        for b, c in zip(art.balls, balls_w, strict=True):
            cc = np.broadcast_to(c, (n, 3))
            gap = point_par(cc, p0, e1, e2) - r - b.diameter_mm / 2
            rows.append(gap - standoff + TOL_MM)
            why.append((f"{body.name} comes {{:.3f}} mm from ball {b.id}", standoff))
            foot = c - np.array([0.0, 0.0, b.rod_length_mm])
            gap = seg_par(cc, np.broadcast_to(foot, (n, 3)), p0, e1, e2) - r - b.rod_diameter_mm / 2
            rows.append(gap - standoff + TOL_MM)
            why.append((f"{body.name} comes {{:.3f}} mm from the rod of ball {b.id}", standoff))
        # table: lowest point of the cylinder at either end of the segment
        down = r * np.sqrt(np.clip(1.0 - stem[:, 2] ** 2, 0.0, 1.0))
        low = []
        for p in (pa, pb):
            ends = np.stack([p + stem * body.from_mm, p + stem * body.to_mm])  # (2, n, 3)
            k = np.argmin(ends[:, :, 2], axis=0)
            low_end = ends[k, np.arange(n)]
            over = np.linalg.norm(low_end[:, :2], axis=1) < t.radius_mm + r
            low.append(np.where(over, low_end[:, 2] - down, np.inf))
        rows.append(np.minimum(*low) - (t.surface_z_mm + t.clearance_mm) + TOL_MM)
        why.append((f"{body.name} comes {{:.3f}} mm from the table keep-out (surface z "
                    f"{t.surface_z_mm:g} + clearance {t.clearance_mm:g} mm)", 0.0))
        for box in prog.machine_file.keep_out:
            lo, hi = np.array(box.min_mm) - r, np.array(box.max_mm) + r
            hit = (seg_box(pa + stem * body.from_mm, pa + stem * body.to_mm, lo, hi)
                   | seg_box(pb + stem * body.from_mm, pb + stem * body.to_mm, lo, hi)
                   | seg_box(p0, p0 + e1, lo, hi))
            rows.append(np.where(hit, -1.0, np.inf))
            why.append((f"{body.name} enters keep-out box {box.name}", 0.0))
    every = np.stack(rows)
    tight = np.argmin(every, axis=0)

    def explain(j: int) -> str:
        template, offset = why[int(tight[j])]
        return template.format(float(every[tight[j], j]) + offset - TOL_MM)

    return every[tight, np.arange(n)], explain
