"""Compensation write-back on LinuxCNC 2.9 (headless, HAL probe carrying the demo link errors,
4-pose plan), one story in three runs on the session's LinuxCNC: a start-of-shift run the CNC
starts, compensated unattended (guards.unattended: true; halcmd setp live, HAL file patched,
read back) and verified at once by a second run against the compensated controller; a
kinematics change outside rumba refused; ``rumba compensate --rollback`` restoring pins and HAL
file; the rolled-back run confirmed again only as a new decision (``--again``) with ``--verify``
(the third run). The before/after claims on both verifications.

The demos.compensate flow; run with ``pytest -m linuxcnc`` (``make test-linuxcnc``).
"""

from __future__ import annotations

import asyncio
import math
import shutil
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml

from daemon.compensation import journal as cj
from daemon.compensation.propose import ControllerModelError, controller_model
from daemon.config import load_daemon_config
from daemon.service.service import Service
from daemon.store.journal import Store
from demos.compensate import MACHINE_NAME, daemon_yaml, demo_machine_file, judge
from drivers.linuxcnc import halkins
from identification.estimate import coverage_factor
from tests.cli_helpers import run_cli
from tests.linuxcnc_helpers import PLAN

pytestmark = [pytest.mark.linuxcnc,
              pytest.mark.skipif(shutil.which("linuxcnc", path="/usr/bin") is None,
                                 reason="LinuxCNC not installed (bash .ci/install-peers.sh "
                                        "linuxcnc)")]

PIN = "xyzbc-trt-kins.x-offset"


@dataclass
class Story:
    cfg: Path
    hal: Path
    first: str  # started by the CNC, compensated unattended
    second: str  # the verification run the daemon started at once


async def _unattended(cfg: Path) -> tuple[str, str]:
    svc = Service(load_daemon_config(cfg))
    await svc.start()
    try:
        session = svc.sessions[MACHINE_NAME]
        first = session.start("cnc")
        await session.wait()
        second = session.run_id
        assert second != first, f"no verification run followed: {session.status()}"
        status = await session.wait()
        assert status["state"] == "IDLE", (status.get("reason"), status)
    finally:
        await svc.stop()
    return first, second


@pytest.fixture(scope="module")
def story(lcnc, tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    """The first two runs, on the session's LinuxCNC as shipped (put back afterwards)."""
    tmp = tmp_path_factory.mktemp("compensate")
    lcnc.reset()
    fifo = (lcnc.peer.dir / "fifo.path").read_text().strip()
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("RTAPI_FIFO_PATH", f"{fifo}/rtapi_fifo")
        try:
            assert f"setp {PIN} 12.5\n" in lcnc.hal_file.read_text()
            machine = demo_machine_file(tmp)
            data = yaml.safe_load(machine.read_text())
            data["controller_kinematics"]["guards"]["unattended"] = True
            machine.write_text(yaml.safe_dump(data, sort_keys=False))
            cfg = tmp / "daemon.yaml"
            cfg.write_text(daemon_yaml(tmp, lcnc.peer.port, PLAN, machine))
            first, second = asyncio.run(_unattended(cfg))
            yield Story(cfg, lcnc.hal_file, first, second)
        finally:
            lcnc.reset()


def _links_before_after(store: Store, run1: str, run2: str) -> None:
    """EX0C −106 µm in the compensating run, zero within k·u_c in its verification."""
    a1, a2 = store.analysis(run1), store.analysis(run2)
    assert a1 is not None and a2 is not None
    k = coverage_factor(a2.estimation.sigma_dof or math.inf)
    ex1, ex2 = a1.links["EX0C"], a2.links["EX0C"]
    assert abs(ex1.value + 106) <= k * ex1.std
    assert abs(ex2.value) <= k * math.hypot(ex1.std, ex2.std), (ex2.value, ex2.std)


def test_unattended_start_of_shift_compensates_and_verifies(story: Story) -> None:
    # guards.unattended: true — a run the CNC starts is followed, with no operator, by the
    # write (within the guards) and at once by a verification run against the new model
    conf = load_daemon_config(story.cfg)
    store = Store(conf.store_path)
    try:
        (row,) = cj.rows(store)
        assert (row.state, row.confirmed_by, row.run_id) == ("applied", "unattended",
                                                             story.first)
        assert row.verify_run_id == story.second and store.run(story.second).trigger == "rerun"
        (v,) = row.values
        assert v.address == PIN and abs(v.new - 12.606) < 0.003  # EX0C −106 µm held by +106
        _links_before_after(store, story.first, story.second)
        # someone changes the kinematics by hand: the next identification refuses
        setup = conf.machines[MACHINE_NAME]
        halkins.setp(PIN, 12.7)
        try:
            with pytest.raises(ControllerModelError, match="outside rumba"):
                controller_model(setup, store)
        finally:
            halkins.setp(PIN, v.new)
        controller_model(setup, store)
    finally:
        store.close()
    # live (halcmd getp prints 7 significant digits: 10 nm at 12.6 mm) and in the HAL file
    assert halkins.getp(PIN) == pytest.approx(v.new, abs=1e-5)
    assert f"setp {PIN} {v.new:.6f}\n" in story.hal.read_text()  # survives a restart
    assert len(list(story.hal.parent.glob("rumba_xyzbc.hal.rumba-*.bak"))) == 1
    outcome = judge(story.cfg, story.first, story.second)
    assert outcome.ok, "\n".join(outcome.lines)
    assert set(outcome.before) == {"EX0C"}
    assert outcome.distortion_after_um <= 0.1 * outcome.distortion_before_um


def test_rollback_then_confirm_again_with_verify_on_linuxcnc(story: Story, capsys) -> None:
    cfg, hal = str(story.cfg), story.hal
    code, out, _ = run_cli(["compensate", "--config", cfg, "--rollback", "--machine",
                            MACHINE_NAME, "--by", "operator"], capsys)
    assert code == 0, out
    assert halkins.getp(PIN) == 12.5
    assert f"setp {PIN} 12.500000\n" in hal.read_text()
    assert len(list(hal.parent.glob("rumba_xyzbc.hal.rumba-*.bak"))) == 2
    conf = load_daemon_config(story.cfg)
    setup = conf.machines[MACHINE_NAME]
    store = Store(conf.store_path)
    try:
        assert [r.state for r in cj.rows(store)] == ["rolled_back", "rolled_back"]
        assert controller_model(setup, store).axes == setup.machine.axes
    finally:
        store.close()
    # the rolled-back run again: only as a new decision, and then with the CLI's --verify
    code, out, _ = run_cli(["compensate", "--config", cfg, "--confirm", story.first, "--by",
                            "demo"], capsys)
    assert code == 2 and "--again" in out and halkins.getp(PIN) == 12.5, out
    code, out, _ = run_cli(["compensate", "--config", cfg, "--confirm", story.first, "--again",
                            "--by", "demo", "--verify"], capsys)
    assert code in (0, 1), out  # the verdict of the verification run: PASS/WARN or FAIL
    assert "set live with halcmd and read back" in out
    assert "verification run " in out and "EX0C" in out
    store = Store(conf.store_path)
    try:
        row = cj.rows(store)[-1]
        (v,) = row.values
        assert (row.state, row.confirmed_by, row.run_id) == ("applied", "demo", story.first)
        assert abs(v.new - 12.606) < 0.003
        third = store.runs(MACHINE_NAME, 1)[0].id
        assert third not in (story.first, story.second) and f"verification run {third}" in out
        assert row.verify_run_id == third
        _links_before_after(store, story.first, third)
    finally:
        store.close()
    assert halkins.getp(PIN) == pytest.approx(v.new, abs=1e-5)
    assert f"setp {PIN} {v.new:.6f}\n" in hal.read_text()
    assert len(list(hal.parent.glob("rumba_xyzbc.hal.rumba-*.bak"))) == 3
    outcome = judge(story.cfg, story.first, third)
    assert outcome.ok, "\n".join(outcome.lines)
