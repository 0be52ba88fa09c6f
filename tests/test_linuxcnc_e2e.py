"""End to end against LinuxCNC 2.9 (config/linuxcnc/, xyzbc-trt-kins, HAL probe from our truth):
kinematics cross-check; a verification run, a missed ball, an abort and a killed LinuxCNC, each
through linuxcncrsh (remote, MDI streaming) and through the ``linuxcnc`` module (local, AUTO run
of a program file); local MDI streaming on one pose; temperature channels (HAL pins) read during
the remote verification run.

One LinuxCNC for the session (tests/conftest.py ``lcnc``; only one can run per machine:
simulators.linuxcnc_peer serialises with a flock and always stops it, cleaning shared memory).
Run with ``pytest -m linuxcnc``.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import math
import os
import shutil
import signal
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from contracts.setup_files import load_artefact, load_machine
from contracts.temperatures import TemperatureChannel
from daemon.machines.setup import MachineSetup
from daemon.run.session import State
from daemon.store.temperatures import temperatures
from drivers.registry import make_link
from identification.estimate import coverage_factor
from identification.kinematics import ChainState, frames, to_model
from identification.outliers import split_repeat
from simulators import linuxcnc_peer
from simulators.hal_probe import sensor_c
from tests.linuxcnc_helpers import (
    ARTEFACT,
    MACHINE,
    THERMAL,
    VARIANTS,
    Rsh,
    _link,
    _overshoot_um,
    _session,
    _setup,
    _xfail_on_race,
    halcmd,
)

pytestmark = [pytest.mark.linuxcnc,
              pytest.mark.skipif(shutil.which("linuxcnc", path="/usr/bin") is None,
                                 reason="LinuxCNC not installed (bash .ci/install-peers.sh "
                                        "linuxcnc)")]


def test_forward_kinematics_match_xyzbc_trt_kins(lcnc) -> None:
    """Our nominal chain (WCBFXYZT, B/C point_mm) vs LinuxCNC's xyzbc-trt-kins: joints set in
    identity kinematics (M429), then M428 recomputes the world position from the same joints."""
    peer = lcnc.peer
    machine, _ = load_machine(MACHINE)
    rng = np.random.default_rng(2026)
    joints = np.column_stack([rng.uniform(-150, 150, 50), rng.uniform(-150, 150, 50),
                              rng.uniform(-100, 300, 50), rng.uniform(-90, 90, 50),
                              rng.uniform(-400, 400, 50)])
    # visit them nearest-first in move time (200 mm/s, 360 deg/s): a shorter test, same samples
    scaled, order, left = joints / [200, 200, 200, 360, 360], [0], set(range(1, 50))
    while left:
        nxt = min(left, key=lambda k: np.max(np.abs(scaled[k] - scaled[order[-1]])))
        order.append(nxt)
        left.remove(nxt)
    joints = joints[order]
    balls = range(len(load_artefact(ARTEFACT).balls))
    for k in balls:  # random moves would run the stylus through the balls
        halcmd(peer, "setp", f"rumba-probe.ball-{k}-present", "0")
    rsh = Rsh(peer.port)
    got, used = [], []
    try:
        rsh.home_mdi()
        for q in joints:
            rsh.mdi("M429")
            rsh.mdi("G0 X{:.6f} Y{:.6f} Z{:.6f} B{:.6f} C{:.6f}".format(*q))
            rsh.mdi("M428")
            jp = rsh.floats("get joint_pos")[:5]
            world = rsh.floats("get abs_act_pos")  # X Y Z A B C, always six
            used.append(jp)
            got.append([*world[:3], world[4], world[5]])
        rsh.mdi("M429")
    finally:
        rsh.close()
        for k in balls:
            halcmd(peer, "setp", f"rumba-probe.ball-{k}-present", "1")
    used_a, got_a = np.array(used), np.array(got)
    assert np.max(np.abs(used_a - joints)) < 1e-5  # LinuxCNC went where we asked
    qm = to_model(machine, {k: used_a[:, i] for i, k in enumerate("XYZBC")})
    f_w, f_t = frames(machine, qm, ChainState())
    tip_f = f_t[:, :3, 3]  # tool tip 0: the tool frame origin
    tip_w = np.einsum("sji,sj->si", f_w[:, :3, :3], tip_f - f_w[:, :3, 3])
    dev = np.abs(tip_w - got_a[:, :3])
    assert dev.max() < 1e-4, f"max |ours - xyzbc-trt-kins| = {dev.max():.2e} mm"
    assert np.allclose(got_a[:, 3:], used_a[:, 3:], atol=1e-6)  # rotary world = joint
    # the check can fail: a wrong pivot (x-offset sign) would be tens of mm off
    assert np.abs(tip_w - used_a[:, :3]).max() > 10.0


@dataclass
class Ran:
    """A verification run on the session's LinuxCNC, and what LinuxCNC showed right after it
    (before another test's link writes its verdict or loads a program)."""

    setup: MachineSetup
    status: dict
    hits: list
    analysis: Any
    readings: list  # temperature channels' readings (daemon/store/temperatures.py)
    verdict_pins: tuple[float, float]  # motion.analog-out-00 (code), -01 (verdicts written)
    programs_left: list[Path]  # the local AUTO run's program folder after the run
    mdi_after: tuple[str, ...]  # set mode mdi, set mdi M429 (an MDI O-word call), get error


async def _verification_run(lcnc: Any, tmp: Path, variant: str,
                            channels: tuple[TemperatureChannel, ...] = ()) -> Ran:
    peer = lcnc.peer
    programs = tmp / "programs"  # local AUTO: the per-run program file goes here
    programs.mkdir()
    setup = _setup(_link(peer, variant, **({"program_dir": str(programs)}
                                           if variant == "local-auto" else {})))
    setup = dataclasses.replace(setup, temperatures=channels)
    rsh = Rsh(peer.port)  # before the link connects: linuxcncrsh enables one client at a time
    try:  # zero what a previous link wrote back (a new link counts its verdicts from 1)
        rsh.home_mdi()
        rsh.mdi("M68 E0 Q0")
        rsh.mdi("M68 E1 Q0")
    finally:
        rsh.close()
    session, store = await _session(setup, tmp)
    try:
        run_id = session.start("cli")
        status = await asyncio.wait_for(session.wait(), 600)
        hits, analysis = store.hits(run_id), store.analysis(run_id)
        readings = temperatures(store, run_id)
        pins = (float(halcmd(peer, "getp", "motion.analog-out-00")),
                float(halcmd(peer, "getp", "motion.analog-out-01")))
        left = sorted(programs.iterdir())
        rsh = Rsh(peer.port)
        try:
            mdi_after = (rsh.ask("set mode mdi"), rsh.ask("set mdi M429"), rsh.ask("get error"))
        finally:
            rsh.close()
    finally:
        await session.link.close()
        store.close()
    return Ran(setup, status, hits, analysis, readings, pins, left, mdi_after)


@pytest.fixture(scope="module")
def remote_run(lcnc: Any, tmp_path_factory: pytest.TempPathFactory) -> Ran:
    """The remote verification run, with two temperature channels: the session's
    HAL probe's warming ``temp-z`` pin and a pin that does not exist. One run for both tests
    that check it (a 4-pose run costs ~90 s of real-time motion)."""
    fifo = (lcnc.peer.dir / "fifo.path").read_text().strip()
    channels = (TemperatureChannel(name="spindle", address="rumba-probe.temp-z"),
                TemperatureChannel(name="gone", address="rumba-probe.temp-q"))
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("RTAPI_FIFO_PATH", f"{fifo}/rtapi_fifo")  # the daemon's halcmd → this HAL
        return asyncio.run(_verification_run(lcnc, tmp_path_factory.mktemp("remote"),
                                             "remote", channels))


@pytest.mark.parametrize("variant", VARIANTS)
def test_verification_run_identifies_injected_links(lcnc, tmp_path: Path, variant: str,
                                                    request) -> None:
    if variant == "remote":
        ran: Ran = request.getfixturevalue("remote_run")
    else:
        ran = asyncio.run(_verification_run(lcnc, tmp_path, variant))
    setup, status, hits, analysis = ran.setup, ran.status, ran.hits, ran.analysis
    _xfail_on_race(variant, status["reason"])
    assert status["state"] == str(State.IDLE), status["reason"]
    # every planned touch once; a visit the outlier test names is re-probed after the
    # program (whole poses, all balls: daemon/run/reprobe.py) and journaled beside it as
    # round >= 1 (CI saw one pose re-probed on a loaded box: 100 hits, the run right)
    rounds = [split_repeat(h.repeat)[1] for h in hits]
    planned = len(setup.plan.poses) * 4 * 5
    assert rounds.count(0) == planned
    extra = len(hits) - planned
    assert extra % (4 * 5) == 0 and max(rounds) <= setup.reprobe_max, (extra, max(rounds))
    assert analysis is not None
    links = analysis.to_json()["links"]
    injected = lcnc.truth.errors.links
    assert set(links) == set(injected)
    # "within 3 standard uncertainties" at its 99.73 % coverage: u rests on a σ estimated
    # from the run's own residuals (4 poses: ν ≈ 8.3), so k = t(ν) ≈ 4.2, not 3 (GUM G.3);
    # with k = 3 a clean suite of 16 comparisons failed about one run in four (CI did).
    # The run passes only if every link does: the 99.73 % is family-wise (Bonferroni over
    # the links). At 99.73 % per link, 16 comparisons on a nondeterministic LinuxCNC fail
    # ~4 % of clean runs (CI saw EC0B at 4.0 u once); the accuracy itself is the Monte
    # Carlo's claim (benchmarks), this test checks the loop end to end.
    k = coverage_factor(analysis.estimation.sigma_dof or math.inf,
                        1.0 - 0.0027 / len(injected))
    for name, true_v in injected.items():
        v, u = links[name]["value"], links[name]["std"]
        assert abs(v - true_v) <= k * u, f"{name}: {v:.2f} vs {true_v} (u {u:.2f}, k {k:.2f})"
        assert u < 15.0, f"{name}: u {u:.2f} too large to mean anything"
    # the verdict went back to LinuxCNC: motion.analog-out-00 = code, -01 counts verdicts
    code = {"PASS": 1, "WARN": 2, "FAIL": 3, "ERROR": 4}[status["verdict"]["status"]]
    assert ran.verdict_pins == (code, 1)
    # LinuxCNC latched the first servo sample past contact: overshoot small and tight
    over_um = _overshoot_um(lcnc.truth, hits, setup.artefact.ids)
    assert 0.0 < over_um.mean() < 5.0 and over_um.std() < 1.5, (over_um.mean(),
                                                                  over_um.std())
    # the program file is gone and LinuxCNC no longer has it loaded: an MDI O-word call
    # (the M429 remap) would otherwise fail with "cannot reopen file"
    assert ran.programs_left == []
    assert ran.mdi_after == ("SET MODE ACK", "SET MDI ACK", "ERROR OK")


def test_hal_pin_read_at_every_pose_follows_the_warmup(remote_run: Ran) -> None:
    """Temperature channels through LinuxCNC: a HAL pin read with ``halcmd
    getp`` at the start, at every pose and at the end of the remote verification run (the
    HAL probe's ``temp-z`` pin carrying a warm-up), journaled with the hits; a pin that does
    not exist is journaled with halcmd's reason and the run goes on."""
    readings, analysis = remote_run.readings, remote_run.analysis
    assert remote_run.status["state"] == str(State.IDLE), remote_run.status["reason"]
    n_poses = len(remote_run.setup.plan.poses)
    spindle = [r for r in readings if r.channel == "spindle"]
    assert [r.at for r in spindle] == ["start", *["pose"] * n_poses, "end"], spindle
    values = [r.value_c for r in spindle]
    assert all(v is not None for v in values)
    # warming: strictly rising, between the cold value and the state at the run's end
    assert values == sorted(values) and values[-1] > values[0], values
    assert sensor_c(THERMAL, "Z", 0.0) < values[0] and values[-1] < 19.5 + 6.0
    gone = [r for r in readings if r.channel == "gone"]
    assert len(gone) == n_poses + 2 and all(r.value_c is None for r in gone)
    assert "halcmd getp rumba-probe.temp-q failed" in gone[0].error, gone[0]
    t = analysis.temperatures
    assert t["spindle"]["source"] == "spindle: linuxcnc rumba-probe.temp-z"
    assert t["spindle"]["change_c"] == pytest.approx(values[-1] - values[0])


@pytest.mark.parametrize("variant", VARIANTS)
async def test_missing_ball_stops_with_linuxcnc_probe_error(lcnc, tmp_path: Path,
                                                            variant: str) -> None:
    peer = lcnc.peer
    setup = _setup(_link(peer, variant))
    halcmd(peer, "setp", "rumba-probe.ball-0-present", "0")  # B1 removed from the table
    session, store = await _session(setup, tmp_path)
    try:
        run_id = session.start("cli")
        status = await asyncio.wait_for(session.wait(), 120)
        _xfail_on_race(variant, status["reason"])
        assert status["state"] == str(State.FAILED)
        assert "G38.2 move finished without making contact" in status["reason"]
        assert "ball B1" in status["reason"] and "touch seq 1 " in status["reason"]
        assert "G38.2 X-110.3945 Y-90.3945" in status["reason"]  # the block LinuxCNC ran
        assert store.run(run_id).state == "FAILED"
        assert float(halcmd(peer, "getp", "motion.analog-out-00")) == 4  # ERROR written back
    finally:
        await session.link.close()
        rsh = Rsh(peer.port)  # the stylus stopped where B1 would be: lift it, then put B1 back
        try:
            rsh.ask("set mode mdi")
            rsh.mdi("G0 Z400")
        finally:
            rsh.close()
            halcmd(peer, "setp", "rumba-probe.ball-0-present", "1")
        store.close()


async def test_local_mode_through_the_linuxcnc_module(lcnc) -> None:
    """The daemon on the LinuxCNC PC: same program, the ``linuxcnc`` module in a helper."""
    from contracts.setup_files import plan_from_dict
    from daemon.analysis import pipeline
    peer, truth = lcnc.peer, lcnc.truth
    setup = _setup(_link(peer, "local-mdi"))
    plan = plan_from_dict({"name": "one", "stylus_diameter_mm": 6, "poses": [[30, 60]],
                           "standoff_mm": 1, "overtravel_mm": 1, "clearance_mm": 5,
                           "feeds": {"probe_mm_min": 300, "approach_mm_min": 3000}})
    setup = MachineSetup(**{**setup.__dict__, "plan": plan})
    job = pipeline.prepare(setup, "local-1").job
    link = make_link(_link(peer, "local-mdi"))
    try:
        hits = [h async for h in link.run(job)]
    finally:
        await link.close()
    assert [h.seq for h in hits] == list(range(1, 21)) and all(h.triggered for h in hits)
    assert {h.ball for h in hits} == set(setup.artefact.ids)
    over = _overshoot_um(truth, hits, setup.artefact.ids)
    assert 0.0 < over.mean() < 5.0 and over.std() < 1.5, (over.mean(), over.std())


@pytest.mark.parametrize("variant", VARIANTS)
async def test_abort_stops_linuxcnc_mid_run(lcnc, tmp_path: Path, variant: str) -> None:
    peer = lcnc.peer
    session, store = await _session(_setup(_link(peer, variant)), tmp_path)
    try:
        run_id = session.start("cli")
        for _ in range(600):
            if store.hit_count(run_id) >= 2:
                break
            await asyncio.sleep(0.05)
        _xfail_on_race(variant, session.reason)
        assert await session.abort("hmi")
        assert session.state == State.ABORTED
        assert session.reason.startswith("aborted by hmi during "), session.reason
        rsh = Rsh(peer.port)
        try:
            first = rsh.floats("get joint_pos")
            time.sleep(0.5)
            assert rsh.floats("get joint_pos") == first  # the machine stands still
            assert rsh.ask("get program_status") == "PROGRAM_STATUS IDLE"
        finally:
            rsh.close()
        assert store.hit_count(run_id) >= 2
    finally:
        await session.link.close()
        store.close()


@pytest.mark.parametrize("variant", VARIANTS)
async def test_linuxcnc_killed_mid_run_fails_and_keeps_hits(lcnc, tmp_path: Path,
                                                            variant: str) -> None:
    peer = lcnc.peer
    setup = _setup(_link(peer, variant))
    session, store = await _session(setup, tmp_path)
    try:
        run_id = session.start("cli")
        for _ in range(600):
            if store.hit_count(run_id) >= 3:
                break
            await asyncio.sleep(0.1)
        _xfail_on_race(variant, session.reason)
        assert store.hit_count(run_id) >= 3
        # kill -9 the whole instance: the process group and the detached daemons
        fifo = (peer.dir / "fifo.path").read_text().strip()
        with contextlib.suppress(ProcessLookupError):
            os.killpg(peer.pid, signal.SIGKILL)
        # a daemon may exit on its own between the scan and the kill (CI saw it): not an error
        linuxcnc_peer._kill(linuxcnc_peer._instance_pids(fifo), signal.SIGKILL)
        status = await asyncio.wait_for(session.wait(), 60)
        assert status["state"] == str(State.INTERRUPTED)  # the link lost: INTERRUPTED
        want = "linuxcncrsh" if variant == "remote" else "task process milltask"
        assert want in status["reason"], status["reason"]
        kept = store.hits(run_id)
        assert len(kept) >= 3 and all(h.triggered for h in kept)
        assert [h.seq for h in kept] == list(range(1, len(kept) + 1))
    finally:
        await session.link.close()
        store.close()
        lcnc.restart()  # a fresh LinuxCNC for the tests after this one
