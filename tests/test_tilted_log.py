"""The probing log of a tilted-probe program is true: each touch's logged
approach direction (dir_x dir_y dir_z, machine frame) is the program's tool-frame direction at
its pose — the equator touches ⊥ the spindle, the pole against it — not the X-Y diagonal its
touch number names on a table-table machine; the daemon's path (result line → touch table),
the simulator's log rows and the gap diagnosis' pre-travel effect all carry it, and a
table-table machine's log is unchanged."""

from __future__ import annotations

import asyncio
import dataclasses
from pathlib import Path

import numpy as np
import pytest

from contracts.messages import TOUCH_DIRECTIONS
from contracts.result_lines import parse_result_line
from contracts.setup_files import load_artefact, load_machine, load_plan
from daemon.analysis.touch_centres import rows_to_centres
from identification.effect_types import EffectContext
from identification.offset_effects import probe_pretravel
from programs.dialects import get_dialect
from programs.geometry import pose_frame
from programs.toolpath import build_program
from simulators.controller import VirtualController
from simulators.errors_schema import errors_from_dict
from simulators.offline import touches_to_rows
from simulators.truth import TruthModel

CFG = Path(__file__).resolve().parents[1] / "config"
CASES = {  # machine, artefact, plan, dialect
    "swivelhead": ("swivelhead_wcfxyzbt", "vertical_4ball", "swivelhead_12poses", "fanuc"),
    "thesis": ("thesis_wcbxfzyt", "thesis_4ball", "thesis_ch3_7poses", "fanuc"),
}


def _run(name: str):
    mname, aname, pname, dialect = CASES[name]
    machine, mf = load_machine(CFG / f"machines/{mname}.yaml")
    artefact = load_artefact(CFG / f"artefacts/{aname}.yaml")
    plan = load_plan(CFG / f"plans/{pname}.yaml")
    prog = build_program(machine, mf, artefact, plan)
    truth = TruthModel.build(machine, mf, artefact, errors_from_dict(
        {"machine": machine.name, "links": {}, "probe": {"stylus_diameter_mm": 6}}))
    vc = VirtualController(truth, rng_seed=1, dialect=dialect)
    d = get_dialect(dialect)

    async def go() -> str:
        await vc.load_program(d.render(prog), dialect, d.aux_files(prog))
        await vc.start()
        return await vc.wait_done(60)

    assert asyncio.run(go()) == "done", vc.alarm
    return machine, mf, artefact, prog, vc


def _spindles(machine, mf, prog) -> dict[int, np.ndarray]:
    """The nominal spindle direction at each pose of the program."""
    out = {}
    for t in prog.touches:
        if t.id.pose not in out:
            out[t.id.pose] = pose_frame(machine, {machine.rotary_axes[0]: t.b_deg,
                                                  machine.rotary_axes[1]: t.c_deg},
                                        prog.state).spindle
    return out


def test_a_tilted_touch_logs_its_tool_frame_direction() -> None:
    machine, mf, _, prog, vc = _run("swivelhead")
    table = prog.touch_table()
    spindle = _spindles(machine, mf, prog)
    hits = [table.fill(h) for h in map(parse_result_line, vc.printed) if h is not None]
    assert len(hits) == len(prog.touches)
    rows = {r.seq: r for r in touches_to_rows(vc, "r")}
    tilted = 0
    for h in hits:
        s = spindle[h.pose]
        d = np.asarray(h.direction)
        assert d == pytest.approx(np.asarray(table.get(h.seq).direction), abs=1e-12)
        if h.touch == 5:
            assert d == pytest.approx(-s, abs=1e-9), h
        else:
            assert abs(float(d @ s)) < 1e-9 and np.linalg.norm(d) == pytest.approx(1.0), h
        r = rows[h.seq]  # the simulator's log row as the daemon logs it
        assert (r.dir_x, r.dir_y, r.dir_z) == pytest.approx(tuple(d), abs=1e-9)
        if abs(s[2]) < 0.999:
            tilted += 1
            assert not np.allclose(d, TOUCH_DIRECTIONS[h.touch], atol=1e-3)
    assert tilted >= 40  # the B −20° and −40° poses


def test_a_table_table_log_is_unchanged() -> None:
    _, _, _, prog, vc = _run("thesis")
    table = prog.touch_table()
    for h in map(parse_result_line, vc.printed):
        if h is not None:
            assert table.fill(h).direction == pytest.approx(TOUCH_DIRECTIONS[h.touch],
                                                            abs=1e-12)
    for r in touches_to_rows(vc, "r"):
        assert (r.dir_x, r.dir_y, r.dir_z) == pytest.approx(TOUCH_DIRECTIONS[r.touch],
                                                            abs=1e-12)


def test_the_sphere_fit_and_the_pretravel_effect_use_the_logged_direction() -> None:
    """The sphere fit needs only the points (its centre does not move with the logged
    direction); the gap diagnosis' pre-travel effect offsets each touch along its logged
    direction — on a tilted touch the tool-frame one."""
    machine, _, artefact, _, vc = _run("swivelhead")
    rows = touches_to_rows(vc, "r")
    flat = [dataclasses.replace(r, dir_x=TOUCH_DIRECTIONS[r.touch][0],
                                dir_y=TOUCH_DIRECTIONS[r.touch][1],
                                dir_z=TOUCH_DIRECTIONS[r.touch][2]) for r in rows]
    a = rows_to_centres(rows, artefact, vc.truth.stylus_radius_mm).centres
    b = rows_to_centres(flat, artefact, vc.truth.stylus_radius_mm).centres
    assert np.array_equal(a.xyz_mm, b.xyz_mm)
    d = np.array([[r.dir_x, r.dir_y, r.dir_z] for r in rows])
    n = len(rows)
    ctx = EffectContext(np.zeros(n), np.array([r.b_deg for r in rows]),
                        np.array([r.c_deg for r in rows]), np.zeros(n, int),
                        np.array([r.touch for r in rows]), d,
                        np.array([[r.x_mm, r.y_mm, r.z_mm] for r in rows]), np.zeros((n, 3)),
                        np.zeros(n))
    eff = probe_pretravel(machine, None)
    off = eff.touch_offset_mm(np.full(5, 2.0), ctx)
    assert off == pytest.approx(2e-3 * d, abs=1e-12)
