"""Compensation proven on LinuxCNC's own kinematics for a head family:
LinuxCNC 2.9 running rumba's swivel-head kins module (config/linuxcnc/xyzbc_head_kins.comp,
built with halcompile, installed into LinuxCNC's module folder), the HAL probe carrying the
injected link errors. The module's forward kinematics against our chain with every pin off
nominal; then the demos.compensate_head story: verification run, ``rumba compensate --confirm``
(pins live + HAL file), verification run against the compensated controller — every
compensable link within k·u_c of zero — and ``--rollback`` restoring pins and HAL file.

Only one LinuxCNC runs per machine: the module stops the session's trunnion LinuxCNC
(tests/conftest.py ``lcnc``) and starts it again afterwards. Run with ``pytest -m linuxcnc``.
"""

from __future__ import annotations

import asyncio
import math
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from contracts.controller_kinematics import controller_kinematics
from contracts.setup_files import load_machine
from daemon.compensation import journal as cj
from daemon.config import load_daemon_config
from daemon.store.journal import Store
from demos import compensate_head as demo
from demos.compensate import judge, verification
from identification.compensation import ParamChange, apply_changes
from identification.estimate import coverage_factor
from identification.kinematics import ChainState, frames, to_model
from simulators import linuxcnc_peer
from tests.cli_helpers import run_cli
from tests.linuxcnc_helpers import Rsh, halcmd

pytestmark = [pytest.mark.linuxcnc,
              pytest.mark.skipif(shutil.which("linuxcnc", path="/usr/bin") is None
                                 or shutil.which("halcompile", path="/usr/bin") is None,
                                 reason="LinuxCNC or halcompile not installed (bash "
                                        ".ci/install-peers.sh linuxcnc)")]

ROOT = Path(__file__).resolve().parents[1]
PREFIX = "xyzbc-head-kins."
COMPENSABLE = {"EX0C": "c-x", "EA0C": "c-tilt-a", "EB0C": "c-tilt-b", "EA0B": "b-tilt-a",
               "EC0B": "b-tilt-c"}


def _mdi(rsh: Rsh, block: str) -> None:
    """``rsh.mdi`` naming LinuxCNC's answer and error when it refuses the block."""
    ack = rsh.ask(f"set mdi {block}")
    err = rsh.ask("get error")
    assert (ack, err) == ("SET MDI ACK", "ERROR OK"), (block, ack, err,
                                                       rsh.ask("get joint_pos"))


@dataclass
class Head:
    work: Path
    peer: linuxcnc_peer.Peer
    truth: object

    @property
    def hal_file(self) -> Path:
        return self.peer.dir / "config" / "rumba_swivelhead.hal"


@pytest.fixture(scope="module")
def head(lcnc, tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    """The swivel head's LinuxCNC in place of the session's (put back afterwards)."""
    linuxcnc_peer.down(lcnc.peer.dir)
    try:
        work = tmp_path_factory.mktemp("head")
        truth, peer = demo.start_peer(work)
        fifo = (peer.dir / "fifo.path").read_text().strip()
        try:
            with pytest.MonkeyPatch.context() as mp:
                mp.setenv("RTAPI_FIFO_PATH", f"{fifo}/rtapi_fifo")  # halkins → this HAL
                yield Head(work, peer, truth)
        finally:
            linuxcnc_peer.down(peer.dir)
    finally:
        lcnc.restart()


def test_head_kins_forward_match_our_chain(head: Head) -> None:
    """Every pin off nominal (pivots by tenths of a mm, tilts by 0.01-0.03°): the module's
    tool-centre point (M428) of random joints equals the tip in the table frame of our chain
    with the controller model those pin values stand for (identification.compensation's
    apply_changes: a pivot moves point_mm, a tilt is a held link)."""
    machine, mfile = load_machine(ROOT / "config" / demo.MACHINE)
    ck = controller_kinematics(mfile.controller_kinematics, machine, "machine")
    pivots = {"c-x": 0.25, "c-y": -0.15, "b-x": 0.12, "b-z": -0.3}
    tilts_deg = {"c-tilt-a": 0.011, "c-tilt-b": -0.017, "b-tilt-a": 0.023, "b-tilt-c": -0.029}
    changes = [ParamChange(n, "pivot", v, 0.0, True, "test") for n, v in pivots.items()]
    changes += [ParamChange(n, "orientation", math.radians(v), 0.0, True, "test")
                for n, v in tilts_deg.items()]
    ctrl = apply_changes(machine, ck.to_math(), changes)
    pins = {ck.param(n).address: v for n, v in {**pivots, **tilts_deg}.items()}
    rng = np.random.default_rng(24)
    joints = np.column_stack([rng.uniform(-200, 200, 12), rng.uniform(-150, 150, 12),
                              rng.uniform(350, 750, 12), rng.uniform(-90, 20, 12),
                              rng.uniform(-300, 300, 12)])
    for k in range(4):  # random moves would run the stylus through the balls
        halcmd(head.peer, "setp", f"rumba-probe.ball-{k}-present", "0")
    rsh = Rsh(head.peer.port)
    got, used = [], []
    try:
        for pin, v in pins.items():
            halcmd(head.peer, "setp", pin, repr(v))
        rsh.home_mdi()
        for q in joints:
            _mdi(rsh, "M429")
            _mdi(rsh, "G0 X{:.6f} Y{:.6f} Z{:.6f} B{:.6f} C{:.6f}".format(*q))
            _mdi(rsh, "M428")
            used.append(rsh.floats("get joint_pos")[:5])
            world = rsh.floats("get abs_act_pos")  # X Y Z A B C
            got.append([*world[:3], world[4], world[5]])
        _mdi(rsh, "M429")
    finally:
        rsh.close()
        for pin in pins:
            halcmd(head.peer, "setp", pin, "0")
        for k in range(4):
            halcmd(head.peer, "setp", f"rumba-probe.ball-{k}-present", "1")
    used_a, got_a = np.array(used), np.array(got)
    assert np.max(np.abs(used_a - joints)) < 1e-5  # LinuxCNC went where we asked
    qm = to_model(ctrl, {k: used_a[:, i] for i, k in enumerate("XYZBC")})
    f_w, f_t = frames(ctrl, qm, ChainState(links=dict(ctrl.held_links)))
    tip_f = f_t[:, :3, :3] @ np.asarray(ctrl.tool_tip_mm) + f_t[:, :3, 3]
    tip_w = np.einsum("sji,sj->si", f_w[:, :3, :3], tip_f - f_w[:, :3, 3])
    assert np.max(np.abs(got_a[:, 3:] - used_a[:, 3:])) < 1e-6  # B C pass through
    # 6 decimals printed by linuxcncrsh; a sign or order slip in any pin is ≥ 10 µm here
    err = np.max(np.abs(got_a[:, :3] - tip_w))
    assert err < 1e-4, err
    # and nominal pins are a different chain: the check is not blind to the pins
    f_w0, f_t0 = frames(machine, qm, ChainState())
    tip0 = f_t0[:, :3, :3] @ np.asarray(machine.tool_tip_mm) + f_t0[:, :3, 3]
    tip0_w = np.einsum("sji,sj->si", f_w0[:, :3, :3], tip0 - f_w0[:, :3, 3])
    assert np.max(np.abs(got_a[:, :3] - tip0_w)) > 0.05


@dataclass
class Story:
    cfg: Path
    first: str
    second: str


@pytest.fixture(scope="module")
def story(head: Head) -> Story:
    """Verification run, ``rumba compensate --confirm``, verification run (as the demo)."""
    from daemon.cli.main import main as rumba

    cfg = head.work / "daemon.yaml"
    cfg.write_text(demo.daemon_yaml(head.work, head.peer.port, demo.PLAN,
                                    demo.demo_machine_file(head.work)))
    first = asyncio.run(verification(cfg, "before", demo.MACHINE_NAME))
    code = rumba(["compensate", "--config", str(cfg), "--confirm", first, "--by", "test"])
    assert code == 0, f"rumba compensate --confirm {first}: exit {code}"
    second = asyncio.run(verification(cfg, "after", demo.MACHINE_NAME))
    return Story(cfg, first, second)


def _pins() -> dict[str, float]:
    from drivers.linuxcnc import halkins

    return halkins.read_pins([PREFIX + p for p in ("c-x", "c-y", "b-x", "b-z", "ea0c-deg",
                                                   "eb0c-deg", "ea0b-deg", "ec0b-deg")])


def test_compensated_head_links_within_uncertainty_of_zero(head: Head, story: Story) -> None:
    conf = load_daemon_config(story.cfg)
    store = Store(conf.store_path)
    try:
        (row,) = cj.rows(store)
        assert (row.state, row.run_id) == ("applied", story.first)
        written = {v.name: v for v in row.values}
        # what probing sees: c-x and the four tilts; b-x, b-z, c-y are left (not observable)
        assert set(written) == set(COMPENSABLE.values()), sorted(written)
        a1 = store.analysis(story.first)
        assert a1 is not None
        k1 = coverage_factor(a1.estimation.sigma_dof or math.inf, 0.9973)
        truth = head.truth.errors.links  # type: ignore[attr-defined]
        for link in COMPENSABLE:  # the first run found the injected errors (µm / µrad)
            est = a1.links[link]
            assert abs(est.value - truth[link]) <= k1 * est.std, (link, est.value, est.std,
                                                                  truth[link])
    finally:
        store.close()
    live = _pins()
    assert live[PREFIX + "c-x"] == pytest.approx(written["c-x"].new, abs=1e-5)
    # the journal keeps the held link in µrad, the pin in deg (6 decimals: 17 nrad)
    assert live[PREFIX + "ea0b-deg"] == pytest.approx(math.degrees(written["b-tilt-a"].new
                                                                   * 1e-6), abs=1e-6)
    assert live[PREFIX + "b-x"] == 0 and live[PREFIX + "b-z"] == 0 and live[PREFIX + "c-y"] == 0
    text = head.hal_file.read_text()
    assert f"setp {PREFIX}c-x {written['c-x'].new:.6f}\n" in text  # survives a restart
    outcome = judge(story.cfg, story.first, story.second, demo.MACHINE_NAME)
    print("\n".join(outcome.lines))
    assert set(outcome.before) == set(COMPENSABLE), outcome.before
    assert outcome.ok, "\n".join(outcome.lines)
    assert outcome.distortion_after_um <= 0.1 * outcome.distortion_before_um


def _tcp_spread_um(head: Head) -> float:
    """LinuxCNC's own tool-centre point (M428): two points of the table frame commanded at B 0 C
    0 and at four other indexations; where the stylus tip truly lands (the HAL probe's true
    chain: injected link errors, nominal stylus), relative to where it lands at B 0 C 0 — a
    shop sets the part's position (work offset) at one indexation and the TCP must hold it at
    the others. The largest such difference (µm): what a 5-axis program run with TCP on this
    controller would be off by. (The part of a link error the setup absorbs — e.g. EX0C's
    constant offset of the table frame — is a work offset, not a TCP error.)"""
    machine, _ = load_machine(ROOT / "config" / demo.MACHINE)
    links = dict(head.truth.links)  # type: ignore[attr-defined]
    poses = [(0.0, 0.0), (-20.0, 120.0), (-40.0, 240.0), (-30.0, 60.0), (-10.0, 200.0)]
    points = [(60.0, -40.0, 120.0), (-80.0, 50.0, 90.0)]
    targets = [(*p, b, c) for p in points for b, c in poses]
    for k in range(4):  # TCP moves sweep the stylus across the table
        halcmd(head.peer, "setp", f"rumba-probe.ball-{k}-present", "0")
    rsh = Rsh(head.peer.port)
    used = []
    try:
        rsh.home_mdi()
        _mdi(rsh, "M429")
        _mdi(rsh, "G0 Z800")
        _mdi(rsh, "M428")
        for t in targets:
            _mdi(rsh, "G0 X{:.6f} Y{:.6f} Z{:.6f} B{:.6f} C{:.6f}".format(*t))
            used.append(rsh.floats("get joint_pos")[:5])
        _mdi(rsh, "M429")
        _mdi(rsh, "G0 Z800")
    finally:
        rsh.close()
        for k in range(4):
            halcmd(head.peer, "setp", f"rumba-probe.ball-{k}-present", "1")
    q = np.array(used)
    qm = to_model(machine, {k: q[:, i] for i, k in enumerate("XYZBC")})
    f_w, f_t = frames(machine, qm, ChainState(links=links))
    tip_f = f_t[:, :3, :3] @ np.asarray(machine.tool_tip_mm) + f_t[:, :3, 3]
    tip_w = np.einsum("sji,sj->si", f_w[:, :3, :3], tip_f - f_w[:, :3, 3])
    err = (tip_w - np.array(targets)[:, :3]).reshape(len(points), len(poses), 3)
    return float(np.max(np.linalg.norm(err - err[:, :1], axis=2)) * 1e3)


def test_rollback_restores_head_kins_pins(head: Head, story: Story, capsys) -> None:
    before = _pins()
    assert any(abs(v) > 0 for v in before.values())  # the compensation is in place
    compensated_um = _tcp_spread_um(head)
    code, out, _ = run_cli(["compensate", "--config", str(story.cfg), "--rollback",
                            "--machine", demo.MACHINE_NAME, "--by", "operator"], capsys)
    assert code == 0, out
    assert all(v == 0 for v in _pins().values()), _pins()
    text = head.hal_file.read_text()
    for name in ("c-x", "ea0c-deg", "eb0c-deg", "ea0b-deg", "ec0b-deg"):
        assert f"setp {PREFIX}{name} 0.000000\n" in text, name
    conf = load_daemon_config(story.cfg)
    store = Store(conf.store_path)
    try:
        assert [r.state for r in cj.rows(store)][-1] == "rolled_back"
    finally:
        store.close()
    # LinuxCNC's kinematics is what the write-back changed: with the pins as written its TCP
    # holds a point of the part within a few µm over the indexations, with the nominal pins it
    # carries the injected link errors (tens of µm: EX0C's circle, the tilts at a 370 mm lever)
    nominal_um = _tcp_spread_um(head)
    print(f"TCP spread: nominal pins {nominal_um:.1f} µm, compensated {compensated_um:.1f} µm")
    assert nominal_um > 30.0 and compensated_um < 0.15 * nominal_um, (nominal_um,
                                                                      compensated_um)
    assert os.environ.get("RTAPI_FIFO_PATH", "").startswith("/tmp/rumba-rtapi.")
