"""`rumba plan --map`: placements and poses covering a volume within a machine-time budget, what
each placement adds, the map-job file the daemon loads; refusals (a budget too small, a volume
the placements cannot cover, bad input) in one line naming what to change."""

from __future__ import annotations

import io
from contextlib import redirect_stderr, redirect_stdout

import pytest

from benchmarks.rigs.daemon_helpers import CONFIG
from contracts.map_job import load_map_job
from daemon.cli.main import main
from programs import map_plan

MACHINE = str(CONFIG / "machines/thesis_wcbxfzyt.yaml")
ARTEFACTS = [str(CONFIG / f"artefacts/{a}.yaml")
             for a in ("thesis_4ball_scaled", "thesis_4ball_map2")]


@pytest.fixture(autouse=True)
def generated_once(monkeypatch):
    """The candidate programs (generated and safety-checked, ~1 s each) once per module."""
    monkeypatch.setattr(map_plan, "_candidates", _cached)


_ORIGINAL = map_plan._candidates
_MADE: dict = {}


def _cached(machine_path, artefacts, dialect, settings, tilt_max_deg):
    key = (str(machine_path), tuple(a.name for a in artefacts), dialect, repr(settings),
           tilt_max_deg)
    if key not in _MADE:
        _MADE[key] = _ORIGINAL(machine_path, artefacts, dialect, settings, tilt_max_deg)
    return _MADE[key]


def run_cli(argv: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with redirect_stdout(out), redirect_stderr(err):
        try:
            code = main(argv)
        except SystemExit as e:  # argparse's own refusal of a value
            code = int(e.code or 0)
    return code, out.getvalue(), err.getvalue()


def plan_args(tmp_path, *extra: str) -> list[str]:
    return ["plan", "--map", "--machine", MACHINE, "--artefact", ARTEFACTS[0],
            "--artefact", ARTEFACTS[1], "-o", str(tmp_path / "thesis-map.yaml"), *extra]


def test_a_twenty_minute_map_of_the_thesis_machine_covers_and_says_what_each_adds(tmp_path):
    code, out, err = run_cli(plan_args(tmp_path, "--budget-min", "20"))
    assert code == 0, err
    job = load_map_job(tmp_path / "thesis-map.yaml")  # the daemon's loader accepts it
    assert [p.name for p in job.placements] == ["P1", "P2"]
    assert [p.artefact.name for p in job.placements] == ["thesis-4ball-scaled",
                                                         "thesis-4ball-map2"]
    mp = map_plan.plan_map(MACHINE, ARTEFACTS, 20 * 60)
    assert mp.seconds <= 20 * 60  # the budget, on the cycle-time estimate
    assert [len(s.candidate.plan.poses) for s in mp.steps] == \
        [len(p.plan.poses) for p in job.placements]
    first, second = mp.steps
    # the second placement widens every axis' stroke and sharpens the terms of the first
    assert all(second.added_mm[a] > 100 for a in "XYZ")
    assert len(first.new_terms) > 30 and len(second.better) > 10
    assert all(after * map_plan.BETTER <= before for before, after in second.better.values())
    assert min(mp.coverage.values()) >= 0.5
    assert "P2 thesis-4ball-map2" in out and "better determined" in out
    assert f"total {mp.seconds / 60:.1f} min of machine time" in out


def test_a_smaller_budget_gives_a_shorter_plan_or_a_refusal(tmp_path):
    small = map_plan.plan_map(MACHINE, ARTEFACTS, 8 * 60, min_coverage=0.3)
    assert small.seconds <= 8 * 60
    big = map_plan.plan_map(MACHINE, ARTEFACTS, 20 * 60, min_coverage=0.3)
    assert min(big.coverage.values()) >= min(small.coverage.values())
    code, _, err = run_cli(plan_args(tmp_path, "--budget-min", "8", "--min-coverage", "0.55"))
    assert code == 2 and "budget 8.0 min covers only" in err and "in " in err
    assert not (tmp_path / "thesis-map.yaml").exists()
    code, _, err = run_cli(plan_args(tmp_path, "--budget-min", "0.5"))
    assert code == 2 and "the smallest checked placement program takes" in err


def test_a_volume_beyond_the_placements_reach_is_refused_whatever_the_budget(tmp_path):
    code, _, err = run_cli(plan_args(tmp_path, "--budget-min", "600", "--min-coverage", "1"))
    assert code == 2 and "cannot cover 100 % of the target" in err
    assert "add a placement that reaches further" in err


@pytest.mark.parametrize(("extra", "said"), [
    (["--box", "1,2,3"], "--box: expected X0,X1,Y0,Y1,Z0,Z1"),
    (["--box", "100,-100,0,10,0,10"], "--box: X 100..-100 mm: expected lo < hi"),
    (["--box=-900,0,0,10,0,10"], "within the stroke -350..350 mm"),
    (["--min-coverage", "1.5"], "expected a fraction in (0, 1]"),
    (["--budget-min", "nan"], "expected minutes as a plain decimal"),
])
def test_bad_input_is_one_line(tmp_path, extra, said):
    args = plan_args(tmp_path, *(["--budget-min", "20"] if "--budget-min" not in extra
                                 else []), *extra)
    code, _, err = run_cli(args)
    assert code == 2 and said in err and "Traceback" not in err


def test_map_options_without_map_and_link_targets_with_map_are_refused(tmp_path):
    code, _, err = run_cli(["plan", "--machine", MACHINE, "--artefact", ARTEFACTS[0],
                            "--budget-min", "20"])
    assert code == 2 and "--budget-min: only with --map" in err
    code, _, err = run_cli(plan_args(tmp_path))
    assert code == 2 and "--map: give the machine-time budget --budget-min MIN" in err
