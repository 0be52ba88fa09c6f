"""Temperature channels through LinuxCNC (issue 22 item 3): a HAL pin read with ``halcmd getp``
at the start, at every pose and at the end of a real verification run (LinuxCNC 2.9, the HAL
probe's ``temp-z`` pin carrying a warm-up), journaled with the hits; a pin that does not exist
is journaled with halcmd's reason and the run goes on. Run with ``pytest -m linuxcnc``."""

from __future__ import annotations

import asyncio
import dataclasses
import json
import shutil
from pathlib import Path

import pytest

from contracts.temperatures import TemperatureChannel
from daemon.run.session import State
from daemon.store.temperatures import temperatures
from simulators.hal_probe import sensor_c
from tests.linuxcnc_helpers import Rsh, _link, _session, _setup

pytestmark = [pytest.mark.linuxcnc,
              pytest.mark.skipif(shutil.which("linuxcnc", path="/usr/bin") is None,
                                 reason="LinuxCNC not installed (bash .ci/install-peers.sh "
                                        "linuxcnc)")]
THERMAL = {"ambient_c": 19.5, "start_state": 0.0, "axes": {"Z": [6.0, 600.0]}}


async def test_hal_pin_read_at_every_pose_follows_the_warmup(lcnc, tmp_path: Path,
                                                             monkeypatch) -> None:
    original = lcnc.spec.read_text()
    warm = json.loads(original)
    warm["thermal"] = THERMAL
    lcnc.spec.write_text(json.dumps(warm))
    try:
        lcnc.restart()  # the HAL probe now carries the warm-up: temp-z rises from 19.5 °C
        peer = lcnc.peer
        fifo = (peer.dir / "fifo.path").read_text().strip()
        monkeypatch.setenv("RTAPI_FIFO_PATH", f"{fifo}/rtapi_fifo")  # the daemon's HAL
        setup = dataclasses.replace(_setup(_link(peer, "remote")), temperatures=(
            TemperatureChannel(name="spindle", address="rumba-probe.temp-z"),
            TemperatureChannel(name="gone", address="rumba-probe.temp-q")))
        rsh = Rsh(peer.port)
        try:
            rsh.home_mdi()
        finally:
            rsh.close()
        session, store = await _session(setup, tmp_path)
        try:
            run_id = session.start("cli")
            status = await asyncio.wait_for(session.wait(), 600)
            assert status["state"] == str(State.IDLE), status["reason"]
            readings = temperatures(store, run_id)
            analysis = store.analysis(run_id)
        finally:
            await session.link.close()
            store.close()
    finally:
        lcnc.spec.write_text(original)
        lcnc.restart()
    n_poses = len(setup.plan.poses)
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
