"""Shared set-up for tests/test_linuxcnc_e2e.py: paths, a linuxcncrsh client, halcmd, links."""

from __future__ import annotations

import json
import os
import re
import socket
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from contracts.setup_files import load_artefact, load_machine, load_plan
from daemon.machines.setup import MachineSetup, TriggersFile
from daemon.machines.tolerances import Limit, Tolerances
from daemon.run.session import Session
from daemon.store.journal import Store
from drivers.registry import make_link
from simulators import linuxcnc_peer
from simulators.truth import TruthModel

ROOT = Path(__file__).resolve().parents[1]
MACHINE = ROOT / "config/machines/linuxcnc_xyzbc.yaml"
ARTEFACT = ROOT / "config/artefacts/thesis_4ball.yaml"
ERRORS = ROOT / "config/errors/linuxcnc_xyzbc.yaml"
PLAN = ROOT / "config/plans/linuxcnc_4poses.yaml"
VARIANTS = ("remote", "local-auto")  # linuxcncrsh + MDI streaming; linuxcnc module + AUTO run
RACE = "Queue is not empty after probing"
# The session's HAL probe warms its temp-z pin (temperatures only, no geometric drift:
# simulators/hal_probe.sensor_c), so the remote verification run reads a temperature channel
# on the session's LinuxCNC instead of a run of its own on a restarted one.
THERMAL = {"ambient_c": 19.5, "start_state": 0.0, "axes": {"Z": [6.0, 600.0]}}


def _xfail_on_race(variant: str, reason: str) -> None:
    """LinuxCNC 2.9's own AUTO-mode race after G38.2 (config/linuxcnc/README.md, "Why AUTO is
    not the default"): reported as such, never as a pass, and never hidden in MDI runs."""
    if variant == "local-auto" and RACE in reason:
        pytest.xfail(f"LinuxCNC AUTO race (issues #263/#662/#3650, fix PR #3971): {reason}")


class Rsh:
    """A minimal synchronous linuxcncrsh client for the checks (not the link under test)."""

    def __init__(self, port: int) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=60)
        self.buf = b""
        assert self.ask("hello EMC test 1.0").startswith("HELLO ACK")
        self.sock.sendall(b"set echo off\r\nget echo\r\n")
        while self.line() != "ECHO OFF":
            pass
        for cmd in ("set verbose on", "set enable EMCTOO", "set set_wait done",
                    "set estop off", "set machine on"):
            assert self.ask(cmd).endswith("ACK"), cmd

    def line(self) -> str:
        while True:
            m = re.search(rb"[^\r\n]+[\r\n]", self.buf)
            if m:
                self.buf = self.buf[m.end():]
                return m.group()[:-1].decode()
            data = self.sock.recv(4096)
            assert data, "linuxcncrsh closed"
            self.buf += data

    def ask(self, cmd: str) -> str:
        self.sock.sendall(cmd.encode() + b"\r\n")
        return self.line()

    def mdi(self, block: str) -> None:
        assert self.ask(f"set mdi {block}") == "SET MDI ACK", block
        err = self.ask("get error")
        assert err == "ERROR OK", f"{block}: {err}"

    def home_mdi(self) -> None:
        """Home the joints when needed, then MDI mode."""
        if "NO" in self.ask("get joint_homed").split()[1:6]:
            self.ask("set mode manual")
            self.ask("set home -1")
            for _ in range(100):
                time.sleep(0.1)
                if "NO" not in self.ask("get joint_homed").split()[1:6]:
                    break
        assert self.ask("set mode mdi") == "SET MODE ACK"

    def floats(self, cmd: str) -> list[float]:
        return [float(v) for v in self.ask(cmd).split()[1:]]

    def close(self) -> None:
        self.sock.close()


def halcmd(peer: linuxcnc_peer.Peer, *args: str) -> str:
    fifo = (peer.dir / "fifo.path").read_text().strip()
    env = dict(os.environ, RTAPI_FIFO_PATH=f"{fifo}/rtapi_fifo")
    out = subprocess.run(["/usr/bin/halcmd", *args], env=env, capture_output=True, text=True,
                         timeout=20, check=True)
    return out.stdout.strip()


@dataclass
class Lcnc:
    """The module's LinuxCNC (restarted after a test killed it)."""

    peer: linuxcnc_peer.Peer
    truth: TruthModel
    spec: Path

    def restart(self) -> None:
        linuxcnc_peer.down(self.peer.dir)
        self.peer = linuxcnc_peer.up(self.spec, workdir=self.peer.dir)
        self.reset()

    @property
    def hal_file(self) -> Path:
        return self.peer.dir / "config" / "rumba_xyzbc.hal"

    def reset(self) -> None:
        """Back to the state ``up`` left: the HAL file as shipped (no backups beside it), the
        kinematics pins at its values, every ball on the table (a compensation test writes the
        first two, a missing-ball test the last)."""
        pristine = self.peer.dir / "rumba_xyzbc.hal.pristine"
        if not pristine.exists():
            pristine.write_bytes(self.hal_file.read_bytes())
        self.hal_file.write_bytes(pristine.read_bytes())
        for backup in self.hal_file.parent.glob("rumba_xyzbc.hal.rumba-*"):
            backup.unlink()
        for line in self.hal_file.read_text().splitlines():
            f = line.split()
            if len(f) == 3 and f[0] == "setp" and f[1].startswith("xyzbc-trt-kins."):
                halcmd(self.peer, "setp", f[1], f[2])
        for k in range(len(self.truth.ball_radii_mm)):
            halcmd(self.peer, "setp", f"rumba-probe.ball-{k}-present", "1")


def start_lcnc(work: Path) -> Lcnc:
    """LinuxCNC with the HAL probe carrying the truth of the LinuxCNC sim machine."""
    from simulators.hal_probe import write_spec

    truth = TruthModel.from_files(MACHINE, ARTEFACT, ERRORS)
    spec = work / "probe_spec.json"
    spec.write_text(json.dumps({**write_spec(truth, spec), "thermal": THERMAL}, indent=1))
    state = Lcnc(linuxcnc_peer.up(spec, workdir=work / "peer"), truth, spec)
    state.reset()
    return state


def _link(peer: linuxcnc_peer.Peer, variant: str, **extra: object) -> dict:
    if variant == "remote":
        return {"transport": "linuxcnc", "port": peer.port, "prelude_mdi": ["M429"], **extra}
    run = variant.removeprefix("local-")
    return {"transport": "linuxcnc", "mode": "local", "run": run, "prelude_mdi": ["M429"],
            "local_home": str(peer.dir / "home"), **extra}


def _setup(link: dict) -> MachineSetup:
    m, mf = load_machine(MACHINE)
    plan = load_plan(PLAN)
    link_cfg = make_link(link).cfg
    tol = Tolerances(default_rotation_urad=Limit(warn=100, fail=200),
                     default_translation_um=Limit(warn=300, fail=500))
    return MachineSetup("lcnc", m, mf, load_artefact(ARTEFACT), plan, "linuxcnc", link_cfg,
                        TriggersFile(), tol, 60.0, (), False)


async def _session(setup: MachineSetup, tmp: Path) -> tuple[Session, Store]:
    link = make_link(setup.link)
    await link.connect()
    store = Store(tmp / "journal.sqlite")
    return Session(setup, link, store, tmp / "reports"), store


def _overshoot_um(truth: TruthModel, hits: list, ids: tuple[str, ...]) -> np.ndarray:
    """How far each latched tip centre is inside its true contact sphere (µm)."""
    over = []
    for h in hits:
        a, t = truth.affine_map(h.axes["b"], h.axes["c"])
        tip = a @ np.array([h.axes[k] for k in "XYZ"]) + t
        i = ids.index(h.ball)
        d = np.linalg.norm(tip - truth.ball_centres_mm(0, 0, 0)[i])
        over.append((truth.ball_radii_mm[i] + truth.stylus_radius_mm - d) * 1e3)
    return np.array(over)
