"""Real VirtualController + a real program from the program generator (programs.generate) for
the transport tests: generator → link → front-end → controller → dialect parser, no test double."""

from __future__ import annotations

import pytest

from benchmarks.rigs.sim_helpers import TABLE_B2, truth_with
from contracts.jobs import ProgramJob
from contracts.setup_files import plan_from_dict
from drivers.base import ControllerAlarm
from programs.generate import generate
from simulators.controller import VirtualController
from simulators.truth import TruthModel

# Where the start-of-shift macros read the verdict (gcode_templates/*/README.md), written out
# here as the tests' own oracle for the table the dialects and the simulator share.
MACRO_VERDICT_VARIABLE = {"fanuc": "#598", "haas": "#598", "siemens": "R4",
                          "heidenhain": "Q1598", "linuxcnc": "#3998"}

def make_truth(errors: dict | None = None) -> TruthModel:
    """The thesis machine and 4-ball artefact, Table B.2 link errors by default."""
    return truth_with(TABLE_B2 if errors is None else errors)


def make_job(truth: TruthModel, dialect: str, poses=((0.0, 0.0),)) -> ProgramJob:
    """The generated, safety-checked program for ``poses`` (4 balls × 5 touches each)."""
    plan = plan_from_dict({"name": "transport-test", "poses": [list(p) for p in poses],
                           "stylus_diameter_mm": truth.errors.probe.stylus_diameter_mm})
    g = generate(truth.machine, truth.machine_file, truth.artefact, plan, dialect)
    table = g.touch_table()
    return ProgramJob(run_id="t", text=g.text, dialect=dialect, touch_count=len(table),
                      touches=table, files=dict(g.aux_files), codec=g.dialect)


def real_setup(dialect: str, poses=((0.0, 0.0),), errors: dict | None = None,
               time_scale: float = 0.0) -> tuple[VirtualController, ProgramJob]:
    truth = make_truth(errors)
    job = make_job(truth, dialect, poses)
    vc = VirtualController(truth, time_scale=time_scale, dialect=dialect)
    vc.files.update(job.files)  # what an operator copied to the control beforehand
    return vc, job


def latched_equal(hits, vc: VirtualController, job: ProgramJob, tol_mm: float) -> None:
    """Every hit is the controller's latch (within the transport's resolution), in order."""
    assert [h.seq for h in hits] == list(range(1, job.touch_count + 1))
    r1, r2 = vc.axes[3], vc.axes[4]
    for h, t, tid in zip(hits, vc.touches, job.touches.ids(), strict=True):
        assert (h.pose, h.ball, h.touch) == (tid.pose, tid.ball, tid.touch)
        assert h.triggered == t.triggered
        for k in "XYZ":
            assert abs(h.axes[k] - t.latched[k]) <= tol_mm
        assert abs(h.axes["b"] - t.latched[r1]) <= tol_mm
        assert abs(h.axes["c"] - t.latched[r2]) <= tol_mm


def first_touch_of(job: ProgramJob, ball: str) -> int:
    return min(t.seq for t in job.touches.ids() if t.ball == ball)


async def hits_until_miss(link, job: ProgramJob, miss: int) -> list:
    """Run ``job``; it must end with the controller alarm of the untriggered touch ``miss``.
    Every hit the link yielded before it, the untriggered one last (so it is journaled)."""
    got = []
    with pytest.raises(ControllerAlarm, match=f"did not trigger at touch seq {miss}"):
        async for h in link.run(job):
            got.append(h)
    assert [(h.seq, h.triggered) for h in got] == [(k, k < miss) for k in range(1, miss + 1)]
    return got
