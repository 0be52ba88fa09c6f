"""CAN operator panel on the python-can virtual bus: buttons → daemon session, lamps ← status."""

from __future__ import annotations

import asyncio
import uuid
from types import SimpleNamespace

import can
import pytest

from contracts.yaml_files import ConfigError
from drivers.can.panel import CanPanel, attach, lamp_for
from drivers.can.schema import CanPanelConfig
from simulators.frontends.can import SimulatedPanel
from tests.waiting import until


def channel() -> str:
    return f"rumba-{uuid.uuid4().hex[:8]}"  # a private virtual bus per test


class FakeSession:
    """The daemon session surface the panel uses (start/abort/status/listeners)."""

    def __init__(self) -> None:
        self.listeners: list = []
        self.started: list[str] = []
        self.aborted: list[str] = []
        self.st = {"state": "IDLE", "busy": False, "done": 0, "total": 0, "verdict": None,
                   "link_ok": True}

    def status(self) -> dict:
        return dict(self.st)

    def publish(self, **kw) -> None:
        self.st.update(kw)
        for fn in self.listeners:
            fn(self.status())

    def start(self, trigger: str) -> str:
        if self.st["busy"]:
            raise RuntimeError("run in progress")
        self.started.append(trigger)
        self.publish(busy=True, state="STREAM", total=40, done=0)
        return "run-1"

    async def abort(self, source: str) -> bool:
        self.aborted.append(source)
        self.publish(busy=False, state="ABORTED")
        return True


async def test_buttons_start_and_abort_and_lamps_follow_the_session():
    ch = channel()
    session = FakeSession()
    service = SimpleNamespace(config=SimpleNamespace(path="daemon.yaml"),
                              sessions={"m1": session})
    attached = attach({"interface": "virtual", "channel": ch, "heartbeat_s": 0.05}, service)
    panel = SimulatedPanel(can.Bus(interface="virtual", channel=ch), heartbeat_s=0.05)
    try:
        await panel.wait_lamp("idle")
        panel.press("start", repeats=3)  # a bouncing button is one press
        await panel.wait_lamp("running")
        session.publish(done=10)
        await until(lambda: panel.progress == 25, 10, "the progress frame")
        assert panel.flags & 0x01  # blinking while running
        panel.press("start")  # refused by the session (run in progress): no crash
        await asyncio.sleep(0.05)
        assert session.started == ["can"]
        panel.press("abort")
        await panel.wait_lamp("error")
        assert session.aborted == ["CAN panel"]
        session.publish(state="IDLE", busy=False, verdict={"status": "WARN"})
        await panel.wait_lamp("warn")
        session.publish(link_ok=False)
        await until(lambda: panel.flags & 0x02, 10, "the link down flag")
    finally:
        await attached.close()
        await panel.close()
    assert panel.history == ["idle", "running", "error", "warn"]


async def test_lamp_heartbeat_repeats_the_state():
    ch = channel()
    daemon_side = CanPanel(CanPanelConfig(interface="virtual", channel=ch, heartbeat_s=0.03))
    listener = can.Bus(interface="virtual", channel=ch)
    try:
        daemon_side.set_lamp("pass")
        frames = [await asyncio.to_thread(listener.recv, 10) for _ in range(4)]  # heartbeats
        assert all(f is not None and f.arbitration_id == 0x641 and f.data[0] == 3 for f in frames)
        alive = [f.data[3] for f in frames]
        assert len(set(alive)) == len(alive)  # alive counter advances
    finally:
        listener.shutdown()
        await daemon_side.close()


def test_lamp_mapping():
    assert lamp_for({"busy": True, "done": 3, "total": 12})[:2] == ("running", 25)
    assert lamp_for({"busy": False, "state": "IDLE", "verdict": {"status": "FAIL"}})[0] == "fail"
    assert lamp_for({"busy": False, "state": "FAILED"})[0] == "error"
    assert lamp_for({"busy": False, "state": "IDLE", "verdict": None})[0] == "idle"


async def test_bad_panel_config_is_one_clear_error():
    service = SimpleNamespace(config=SimpleNamespace(path="daemon.yaml"),
                              sessions={"a": FakeSession(), "b": FakeSession()})
    with pytest.raises(ConfigError, match="can_panel: bogus: unknown key"):
        attach({"interface": "virtual", "channel": "x", "bogus": 1}, service)
    with pytest.raises(ConfigError, match="machine: expected one of"):
        attach({"interface": "virtual", "channel": "x"}, service)
    with pytest.raises(ConfigError, match="cannot open"):
        attach({"interface": "nosuchinterface", "channel": "x", "machine": "a"}, service)
