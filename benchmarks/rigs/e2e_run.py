"""A start-of-shift run end to end, the way a shop runs it: ``daemon.yaml`` → ``Service``
against a simulated CNC behind its real front-end (benchmarks/rigs/rig_helpers.py); the CNC
raises its request, the run's verdict arrives on the CNC side (tests/test_e2e_transports.py
checks it, benchmarks/bench_e2e.py times it)."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import Any

import yaml

from benchmarks.rigs.daemon_helpers import CONFIG
from benchmarks.rigs.rig_helpers import Rig
from daemon.config import load_daemon_config
from daemon.machines.setup import MachineSetup
from daemon.run.session import State
from daemon.service.service import Service
from simulators.controller import VERDICT_VARIABLE, VirtualController

PLAN = "thesis_ch3_7poses"  # 7 B/C poses × 4 balls × 5 touches: all 8 links identifiable
RUN_TIMEOUT_S = 60.0
NOISE_SEED = 0  # the simulated probing noise, reseeded per run (tests/test_e2e_transports.py)


def write_config(tmp: Path, dialect: str, link: dict[str, Any], plan: str = PLAN) -> Path:
    doc = {
        "store": {"path": str(tmp / "journal.sqlite")},
        "reports_dir": str(tmp / "reports"),
        "hmi": {"enabled": False},
        "machines": [{
            "name": "mill1",
            "machine": str(CONFIG / "machines/thesis_wcbxfzyt.yaml"),
            "artefact": str(CONFIG / "artefacts/thesis_4ball.yaml"),
            "plan": str(CONFIG / f"plans/{plan}.yaml"),
            "dialect": dialect,
            "link": link,
            "touch_timeout_s": 30,
            "tolerances": {
                "default_rotation_urad": {"warn": 40, "fail": 80},
                "default_translation_um": {"warn": 150, "fail": 300},
                "volumetric_max_um": {"warn": 200, "fail": 400},
            },
        }],
    }
    path = tmp / "daemon.yaml"
    path.write_text(yaml.safe_dump(doc), encoding="utf-8")
    return path


def copy_aux_files(ctrl: VirtualController, setup: MachineSetup) -> None:
    """What the operator copies to a TNC once (format files of FN 16), when the transport
    cannot transfer files (DNC, Modbus mailbox)."""
    from daemon.analysis.pipeline import prepare

    ctrl.files.update(prepare(setup, "setup").job.files)


async def wait_verdict_on_cnc(session: Any, ctrl: VirtualController, timeout_s: float) -> None:
    """Wait until the run has ended and its verdict arrived on the CNC side (the macro waits
    for the verdict variable to become non-zero). A run that ended FAILED or ABORTED raises
    at once with its reason: the CNC will never see a PASS, so waiting longer only hides it."""
    async with asyncio.timeout(timeout_s):
        while session.run_id is None:
            await asyncio.sleep(0.01)
        run_id = session.run_id
        await session.wait()
        if session.state in (State.FAILED, State.ABORTED, State.INTERRUPTED):
            raise AssertionError(f"run {session.run_id} {session.state}: {session.reason}")
        while not (ctrl.verdict and ctrl.done):
            if session.run_id != run_id:  # e.g. a queued repeat of the request
                raise AssertionError(f"run {session.run_id} started after run {run_id}")
            if ctrl.state == "alarm":  # the verdict program will never run to its end
                raise AssertionError(f"run {session.run_id}: CNC in alarm: {ctrl.alarm}")
            await asyncio.sleep(0.01)


def _requests_pending(link: Any) -> int | None:
    """Start requests a serial link still holds for later runs (None: not a serial link)."""
    proto = getattr(link, "_proto", None)
    return proto.requests.qsize() if proto is not None else None


async def run_start_of_shift(rig: Rig, dialect: str, tmp: Path, plan: str = PLAN,
                             requests: int = 1) -> dict[str, Any]:
    """daemon.yaml → Service; the CNC raises its request; returns what the test checks (and
    benchmarks/bench_e2e.py measures: ``marks`` = first time of each session state, and the
    simulated machine time of the probing program)."""
    ctrl = rig.ctrl
    if ctrl.state in ("running", "hold"):
        await ctrl.abort()
    ctrl.dialect = dialect
    ctrl.request = False
    ctrl.reseed(NOISE_SEED)  # the same probing noise whatever ran before on this rig
    cfg = load_daemon_config(write_config(tmp, dialect, rig.link, plan))
    setup = cfg.machines["mill1"]
    if dialect == "heidenhain" and rig.transport != "opcua":
        copy_aux_files(ctrl, setup)
    service = Service(cfg)
    await service.start()
    try:
        session = service.sessions["mill1"]
        marks: dict[str, float] = {}
        machine_s: list[float] = []

        def mark(st: dict[str, Any]) -> None:
            if st["state"] not in marks:
                marks[st["state"]] = time.monotonic()
                if st["state"] == "IDENTIFY":  # every touch is in: the probing program's time
                    machine_s.append(ctrl.machine_time_s)

        session.listeners.append(mark)
        t0 = time.monotonic()
        for _ in range(requests):  # > 1: a macro printing its request line in a loop
            ctrl.raise_start_request()  # the start-of-shift macro / PLC
        await wait_verdict_on_cnc(session, ctrl, RUN_TIMEOUT_S)
        wall_s = time.monotonic() - t0
        out = {"session": session, "trigger": session.trigger, "state": session.state,
               "reason": session.reason, "verdict": session.verdict, "run_id": session.run_id,
               "cnc_verdict": ctrl.verdict, "wall_s": wall_s, "t0": t0, "marks": marks,
               "machine_s": machine_s[0] if machine_s else float("nan"),
               "cnc_variable": ctrl.variables.get(VERDICT_VARIABLE[dialect]),
               "run": service.store.run(session.run_id),
               "analysis": service.store.analysis(session.run_id),
               "runs": [row.id for row in service.store.runs("mill1")],
               "requests_pending": _requests_pending(service.links["mill1"])}
        ctrl.request = False  # the CNC read the verdict and drops its request
        return out
    finally:
        await service.stop()
