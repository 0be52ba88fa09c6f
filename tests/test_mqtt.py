"""Live results on a real mosquitto: every state change, the retained verdict, links and health
with units in the keys, user/password and TLS, and a broker outage that never fails a run."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import aiomqtt
import pytest

from benchmarks.rigs.daemon_helpers import thesis_rows, thesis_setup
from contracts.yaml_files import ConfigError
from daemon.analysis.replay_link import ReplayLink, prepare_from_rows
from daemon.config import read_token_file
from daemon.mqtt.config import MqttConfig, MqttFile, load_mqtt
from daemon.mqtt.publisher import MachinePublisher
from daemon.run.session import Session, State
from daemon.store.journal import Store
from tests.fleet_helpers import start_mosquitto, until
from tests.tls_helpers import make_cert

peer = pytest.mark.peer
PASSWORD = "mqtt-password-0123456789"


@pytest.fixture(scope="module")
def broker():
    b = start_mosquitto()
    yield b
    b.close()


def cfg(port: int, **kw) -> MqttConfig:
    base = dict(host="127.0.0.1", port=port, site="plant1", root="rumba", username=None,
                password=None, tls=None, qos=1, keepalive_s=5, queue_max=1000,
                health_interval_s=60.0)
    return MqttConfig(**{**base, **kw})


class Collector:
    """A subscriber on ``rumba/#`` (as a dashboard would be)."""

    def __init__(self, port: int, **client_kw) -> None:
        self.port, self.kw = port, client_kw
        self.messages: list[tuple[str, dict, bool]] = []
        self.subscribed = asyncio.Event()

    async def run(self) -> None:
        async with aiomqtt.Client("127.0.0.1", self.port, **self.kw) as c:
            await c.subscribe("rumba/#", qos=1)
            self.subscribed.set()
            async for m in c.messages:
                self.messages.append((str(m.topic), json.loads(m.payload), m.retain))

    def on(self, leaf: str) -> list[dict]:
        return [p for t, p, _ in self.messages if t.endswith("/" + leaf)]


async def run_session(tmp_path, pub_cfg: MqttConfig, on_status=None):
    setup = thesis_setup()
    rows = thesis_rows(setup)
    store = Store(tmp_path / "j.sqlite")
    pub = MachinePublisher(pub_cfg, setup.name, store, extra_health=lambda: {"x_rows": 0})
    session = Session(setup, ReplayLink(rows, setup.machine), store, tmp_path / "reports",
                      prepare=prepare_from_rows(rows))
    session.listeners.append(pub.on_status)
    if on_status:
        session.listeners.append(on_status)
    pub.start()
    session.start("cli")
    final = await session.wait()
    return pub, store, final


@peer
async def test_states_verdict_links_and_health_are_published(broker, tmp_path):
    col = Collector(broker.port)
    sub = asyncio.create_task(col.run())
    await asyncio.wait_for(col.subscribed.wait(), 10)
    pub, store, final = await run_session(tmp_path, cfg(broker.port))
    await until(lambda: col.on("health"), what="health")
    states = [p["state"] for p in col.on("state")]
    assert states == ["PREPARE", "STREAM", "CAPTURE", "IDENTIFY", "JUDGE", "WRITE-BACK",
                      "IDLE"]
    assert col.on("state")[-1]["machinery_item_state"] == "NotExecuting"
    assert col.on("state")[2]["machinery_item_state"] == "Executing"
    await until(lambda: any(m["report"] for m in col.on("verdict")), what="report in verdict")
    # the verdict at the run's end says the report is being written; the retained
    # verdict is sent again with the report once it is written
    assert [m["report_state"] for m in col.on("verdict")] == ["writing", "written"]
    v = col.on("verdict")[-1]
    assert v["status"] == final["verdict"]["status"] and v["run_id"] == final["run_id"]
    # the report by file name, never the daemon PC's path
    assert final["verdict"]["report"].startswith(str(tmp_path))
    assert v["report"] == Path(final["verdict"]["report"]).name and "/" not in v["report"]
    links = col.on("links")[-1]["links"]
    assert set(links) == set(store.analysis(final["run_id"]).links)
    assert all(set(d) in ({"value_um", "std_um"}, {"value_urad", "std_urad"})
               for d in links.values())
    assert "value_urad" in links["EA0B"] and any("value_um" in d for d in links.values())
    h = col.on("health")[-1]
    assert h["residual_rms_um"] > 0 and h["mqtt_dropped_messages"] == 0 and h["x_rows"] == 0
    # the figures by the report's name, unit and definition, rounded as shown;
    # the unrounded volumetric_max_um stays for existing subscribers
    figs = {f["key"]: f for f in h["figures"]}
    vol = figs["volumetric_max_um"]
    assert vol["label"] == "max volumetric distortion (probed poses)" and vol["unit"] == "µm"
    assert "every probed ball and pose" in vol["definition"]
    assert vol["value"] == round(h["volumetric_max_um"], 1)
    assert figs["volumetric_after_links_max_um"]["value"] is not None
    assert all(t.startswith("rumba/plant1/mill1/") for t, _, _ in col.messages)
    # a dashboard connecting later gets the last verdict at once (retained)
    late = Collector(broker.port)
    task = asyncio.create_task(late.run())
    await until(lambda: late.on("verdict"), what="retained verdict")
    assert late.on("verdict")[-1]["run_id"] == final["run_id"] and late.messages[0][2]
    await pub.stop()
    for t in (sub, task):
        t.cancel()
    store.close()


@peer
async def test_broker_outage_mid_run_never_fails_it_and_is_repaired(tmp_path):
    b = start_mosquitto()
    try:
        stopped: list[int] = []

        def kill_broker(st: dict) -> None:
            if st["done"] == 20 and not stopped:
                b.stop()
                stopped.append(1)

        pub, store, final = await run_session(tmp_path, cfg(b.port, queue_max=10),
                                              kill_broker)
        assert stopped and final["state"] == State.IDLE and final["verdict"]
        await until(lambda: not pub.connected, what="the publisher to see the outage")
        assert pub.dropped > 0 and len(pub.queue) == 10  # bounded: drop-oldest, counted
        b.start()  # same port
        await until(lambda: pub.connected and not pub.queue, what="the queue to drain")
        late = Collector(b.port)
        task = asyncio.create_task(late.run())
        await until(lambda: late.on("verdict") and late.on("health"), what="repaired topics")
        assert late.on("verdict")[-1]["run_id"] == final["run_id"]
        # counted when the health message was made (later drops are counted after it)
        assert 0 < late.on("health")[-1]["mqtt_dropped_messages"] <= pub.dropped
        assert late.on("state")[-1]["state"] == "IDLE"
        task.cancel()
        await pub.stop()
        store.close()
    finally:
        b.close()


@peer
async def test_user_password_and_tls(tmp_path):
    crt, key = make_cert(tmp_path, "broker")
    b = start_mosquitto(users={"cell7": PASSWORD}, tls=(crt, key))
    try:
        (tmp_path / "pw").write_text(PASSWORD)
        (tmp_path / "pw").chmod(0o600)
        f = MqttFile.model_validate({"host": "127.0.0.1", "port": b.port, "site": "plant1",
                                     "username": "cell7", "password_file": "pw",
                                     "tls": {"ca": str(crt)}})
        good = load_mqtt(f, tmp_path, "daemon.yaml: mqtt", read_token_file)
        col = Collector(b.port, username="cell7", password=PASSWORD, tls_context=good.tls)
        sub = asyncio.create_task(col.run())
        await asyncio.wait_for(col.subscribed.wait(), 10)
        bad = MachinePublisher(cfg(b.port, username="cell7", password="wrong-password-123456",
                                   tls=good.tls), "mill9", Store(tmp_path / "x.sqlite"))
        bad.start()
        bad.publish("health", {"x": 1})
        await until(lambda: "authoriz" in bad.last_error.lower()
                    or "authoris" in bad.last_error.lower(), what="the refusal")
        await bad.stop(0.1)
        pub, store, final = await run_session(tmp_path, good)
        await until(lambda: col.on("verdict"), what="the verdict over TLS")
        assert col.on("verdict")[-1]["run_id"] == final["run_id"]
        assert not any("mill9" in t for t, _, _ in col.messages)
        sub.cancel()
        await pub.stop()
        store.close()
    finally:
        b.close()


def test_mqtt_config_errors(tmp_path):
    with pytest.raises(ValueError, match="one topic level"):
        MqttFile.model_validate({"host": "h", "site": "plant/1"})
    with pytest.raises(ValueError, match="both 'username' and 'password_file'"):
        MqttFile.model_validate({"host": "h", "site": "p", "username": "u"})
    with pytest.raises(ValueError, match=r"Extra inputs|extra"):
        MqttFile.model_validate({"host": "h", "site": "p", "pasword": "x"})
    # a password crosses a network only inside TLS; on loopback it never leaves the PC
    creds = {"site": "p", "username": "u", "password_file": "pw"}
    for host in ("broker.plant", "10.0.0.7", "::ffff:10.0.0.7"):
        with pytest.raises(ValueError, match=r"needs 'tls'.*clear text"):
            MqttFile.model_validate({"host": host, **creds})
        MqttFile.model_validate({"host": host, **creds, "tls": {}})
    for host in ("127.0.0.1", "localhost", "::1"):
        MqttFile.model_validate({"host": host, **creds})
    f = MqttFile.model_validate({"host": "h", "site": "p", "tls": {"ca": "nope.pem"}})
    with pytest.raises(ConfigError, match=r"daemon\.yaml: mqtt\.tls"):
        load_mqtt(f, tmp_path, "daemon.yaml: mqtt", read_token_file)
