"""A chip on a ball through the simulator and the daemon: the simulator's ``chip``
fault, the re-probe after the program (both visits journaled, the clean one used, the verdict
noting the repair) and the ERROR when the fault stays or nothing may be re-probed."""

from __future__ import annotations

import asyncio
from dataclasses import replace

import numpy as np
import pytest
import pytest_asyncio
from pydantic import ValidationError

from benchmarks.rigs.daemon_helpers import CONFIG, thesis_setup, write_daemon_yaml
from daemon.analysis.pipeline import prepare
from daemon.analysis.result import Analysis
from daemon.config import load_daemon_config
from daemon.run.session import Session, State
from daemon.store.journal import Store
from daemon.store.probing_csv import export_csv
from simulators.controller import VirtualController
from simulators.faults import Fault, FaultPlan
from simulators.offline import run_program
from tests.opcua_helpers import opcua_link, thesis_truth

CHIP_AT = (3, "B2", 2)  # pose, ball, touch


def _seq(pose: int, ball: str, touch: int) -> int:
    job = prepare(thesis_setup(), "probe").job
    return next(t.id.seq for t in job.touches
                if (t.id.pose, t.id.ball, t.id.touch) == (pose, ball, touch))


async def test_a_chip_moves_one_touch_once_and_a_stuck_one_every_time():
    setup = thesis_setup()
    one_pose = setup.plan.model_copy(update={"poses": setup.plan.poses[CHIP_AT[0]:][:1]})
    job = prepare(replace(setup, plan=one_pose), "probe").job  # 20 touches
    seq = next(t.id.seq for t in job.touches if (t.id.ball, t.id.touch) == CHIP_AT[1:])
    truth = thesis_truth()
    clean = await run_program(truth, job.text, "fanuc", seed=4)
    for persist in (False, True):
        faults = FaultPlan([Fault(kind="chip", at_touch=seq, size_um=18.0, persist=persist)])
        runs = [await run_program(truth, job.text, "fanuc", seed=4, faults=faults)
                for _ in range(2)]  # the same program twice on the same fault plan
        for n, run in enumerate(runs):
            moved = {r.seq: np.subtract((r.x_mm, r.y_mm, r.z_mm), (c.x_mm, c.y_mm, c.z_mm))
                     for r, c in zip(run.rows, clean.rows, strict=True)
                     if (r.x_mm, r.y_mm, r.z_mm) != (c.x_mm, c.y_mm, c.z_mm)}
            if n == 1 and not persist:
                assert moved == {}  # blown off: a re-probe meets a clean ball
                continue
            (d,) = moved.values()
            assert list(moved) == [seq]
            row = run.rows[seq - 1]
            # 18 µm earlier along the approach: outside the ball, against the direction
            np.testing.assert_allclose(d, -18e-3 * np.array([row.dir_x, row.dir_y, row.dir_z]),
                                       atol=1e-9)
    with pytest.raises(ValidationError, match="at_touch or at_time_s"):
        Fault(kind="chip", at_block=3)


def test_reprobe_max_is_a_checked_daemon_yaml_key(tmp_path):
    cfg = load_daemon_config(write_daemon_yaml(tmp_path))
    assert cfg.machines["mill1"].reprobe_max == 2
    bad = write_daemon_yaml(tmp_path, extra_machine="    reprobe_max: 9")
    with pytest.raises(Exception, match="reprobe_max"):
        load_daemon_config(bad)


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def cnc():
    ctrl = VirtualController(thesis_truth(), time_scale=0.0, dialect="fanuc")
    async with opcua_link(ctrl) as link:
        yield ctrl, link


async def _run(cnc, tmp_path, fault: Fault | None, **setup):
    ctrl, link = cnc
    ctrl.reseed(11)
    ctrl.faults = FaultPlan([fault] if fault else [])
    ctrl.verdict = 0
    s = Session(replace(thesis_setup(), **setup), link, Store(tmp_path / "j.sqlite"),
                tmp_path / "reports")
    run_id = s.start("cli")
    async with asyncio.timeout(120):
        await s.wait()
    assert s.state == State.IDLE, s.reason
    return s, run_id


@pytest.mark.asyncio(loop_scope="module")
async def test_a_chip_is_re_probed_after_the_program_and_the_verdict_notes_it(cnc, tmp_path):
    pose, ball, touch = CHIP_AT
    s, run_id = await _run(cnc, tmp_path, Fault(kind="chip", at_touch=_seq(*CHIP_AT),
                                                size_um=15.0))
    assert s.verdict["status"] == "PASS", s.verdict
    (note,) = [r for r in s.verdict["reasons"] if r.startswith("measurement outlier")]
    assert note.startswith(f"measurement outlier, ball {ball} pose {pose} touch {touch} = +1")
    assert "repaired" in note and "repeat 100" in note
    hits = s.store.hits(run_id)
    assert len(hits) == 140 + 20 and s.total == s.done == 160  # the pose again, 4 balls
    again = hits[140:]
    assert [h.seq for h in again] == list(range(141, 161))  # after the run's, both kept
    assert {(h.pose, h.repeat) for h in again} == {(pose, 100)}
    assert {h.ball for h in again} == {"B1", "B2", "B3", "B4"}
    a = s.store.analysis(run_id)
    (o,) = a.outliers
    assert (o.pose, o.ball, o.touch, o.status, o.replaced_by_repeat) == (
        pose, ball, touch, "repaired", 100)
    assert o.size_um == pytest.approx(15.0, abs=1.5)
    assert a.estimation.centres == 28 and len(s.store.centres(run_id)) == 28
    # the journal as a probing log re-analyses to the same result (re-probe rows included)
    log = tmp_path / "run.csv"
    export_csv(s.store, run_id, log, s.setup.machine)
    from daemon.cli.commands.analyze import run_analysis

    again_a = run_analysis(log, CONFIG / "machines/thesis_wcbxfzyt.yaml",
                           CONFIG / "artefacts/thesis_4ball.yaml")
    assert again_a.outliers == a.outliers
    assert isinstance(a, Analysis)


@pytest.mark.asyncio(loop_scope="module")
async def test_a_fault_that_stays_is_an_error_naming_it(cnc, tmp_path):
    """A chip stuck on the ball: both re-probes meet it (``reprobe_max: 0`` would give the
    same ERROR, "not re-probed": test_outliers.py judges that analysis)."""
    pose, ball, touch = CHIP_AT
    s, run_id = await _run(cnc, tmp_path, Fault(kind="chip", at_touch=_seq(*CHIP_AT),
                                                size_um=25.0, persist=True))
    assert s.verdict["status"] == "ERROR"
    first = s.verdict["reasons"][0]
    assert first.startswith(f"measurement outlier, ball {ball} pose {pose} touch {touch} = +2")
    assert "re-probed 2×, the fault came back (touch 2 +2" in first
    assert "measurement not trusted" in first
    assert s.store.run(run_id).hits == 140 + 2 * 20  # every visit journaled
    assert s.store.analysis(run_id).estimation.centres == 27  # left out of the estimate
    async with asyncio.timeout(10):
        while cnc[0].verdict != 4:  # ERROR reaches the CNC: production must not start
            await asyncio.sleep(0.01)
