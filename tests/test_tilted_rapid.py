"""Tilted-probe transits at rapid where the control's rapid is a straight line:
the program's multi-axis transits are checked as straight lines (``Move.linear_rapid``);
SINUMERIK (after RTLION), Heidenhain (L … FMAX) and LinuxCNC (coordinated G0) run them as
rapids, Fanuc and Haas (G00 non-linear unless parameter 1401 LRP, which a program cannot
set) keep them as G1 at the max feed; the cycle-time model follows the dialect."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest

from contracts.setup_files import load_artefact, load_machine, load_plan
from programs.cycletime import estimate
from programs.generate import generate
from programs.safety import SafetyError, check_program
from programs.toolpath import build_program

CFG = Path(__file__).resolve().parents[1] / "config"
HEADS = {"swivelhead": ("swivelhead_wcfxyzbt", "swivelhead_12poses"),
         "forkhead": ("forkhead_wxfyzcat", "forkhead_11poses")}
LINEAR = {"siemens": True, "heidenhain": True, "linuxcnc": True, "fanuc": False, "haas": False}
_RAPID = {"siemens": re.compile(r"^N\d+ G0 (.*)$"), "linuxcnc": re.compile(r"^N\d+ G0 (.*)$"),
          "fanuc": re.compile(r"^N\d+ G0 (.*)$"), "haas": re.compile(r"^N\d+ G0 (.*)$"),
          "heidenhain": re.compile(r"^\d+ L (.*) R0 FMAX")}


def _load(name: str):
    mname, pname = HEADS[name]
    machine, mf = load_machine(CFG / f"machines/{mname}.yaml")
    return machine, mf, load_artefact(CFG / "artefacts/vertical_4ball.yaml"), \
        load_plan(CFG / f"plans/{pname}.yaml")


def _linear_axes(words: str) -> set[str]:
    return {w[0] for w in words.split() if w[:1] in "XYZ"}


@pytest.mark.parametrize("dialect", sorted(LINEAR))
@pytest.mark.parametrize("name", sorted(HEADS))
def test_checked_transits_run_at_rapid_only_where_rapids_are_straight(name: str,
                                                                     dialect: str) -> None:
    machine, mf, art, plan = _load(name)
    g = generate(machine, mf, art, plan, dialect)
    straight = [mv for mv in g.program.moves if mv.linear_rapid]
    assert len(straight) > 50 and all(mv.kind in ("feed", "retract") for mv in straight)
    lines = g.text.splitlines()
    three = [i for i, ln in enumerate(lines)
             if (m := _RAPID[dialect].match(ln)) and len(_linear_axes(m.group(1))) == 3]
    if LINEAR[dialect]:
        assert len(three) >= 0.5 * len(straight), (len(three), len(straight))
        if dialect == "siemens":  # the linear rapid is switched on before the first one
            assert lines.index("RTLION") < three[0]
    else:  # a non-linear G00 would leave the checked line: never three axes at once
        assert three == [] and "RTLION" not in lines
    # the estimate the header prints follows the dialect
    assert g.cycle_time.estimate_s == pytest.approx(
        estimate(g.program, LINEAR[dialect]).estimate_s)


def test_the_cycle_time_model_times_straight_transits_at_rapid() -> None:
    machine, mf, art, plan = _load("swivelhead")
    prog = build_program(machine, mf, art, plan)
    slow, fast = estimate(prog), estimate(prog, True)
    dyn = mf.dynamics
    dist = 0.0
    pos = None
    for mv in prog.moves:
        tgt = np.array(mv.target[:3])
        if mv.kind == "probe" and mv.touch is not None:
            pos = np.array(mv.touch.contact)
            continue
        if mv.linear_rapid and pos is not None and not np.isnan(pos).any():
            dist += float(np.linalg.norm(tgt - pos))
        if mv.kind != "dwell":
            pos = tgt
    saved = dist / dyn.max_feed_mm_min * 60 - dist / dyn.rapid_mm_min * 60
    assert slow.estimate_s - fast.estimate_s == pytest.approx(saved, rel=1e-9)
    assert fast.ratio < slow.ratio and fast.lower_bound_s == slow.lower_bound_s


def test_the_safety_check_checks_a_straight_transit_on_its_line() -> None:
    """A straight transit moved through a ball is refused: it is checked on the line a linear
    rapid follows (not waved through as a rapid's dog-legs)."""
    machine, mf, art, plan = _load("swivelhead")
    prog = build_program(machine, mf, art, plan)
    check_program(prog)
    i = next(k for k, mv in enumerate(prog.moves) if mv.linear_rapid and mv.kind == "feed")
    mv = prog.moves[i]
    ball = np.array(next(t.centre for t in prog.touches if t.id.pose == mv.pose))
    prev = np.array(prog.moves[i - 1].target[:3])
    through = 2 * ball - prev  # the straight line from the previous point crosses the ball
    prog.moves[i] = dataclasses.replace(mv, target=(*map(float, through), *mv.target[3:]))
    with pytest.raises(SafetyError):
        check_program(prog)
