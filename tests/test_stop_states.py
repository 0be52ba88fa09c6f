"""The end states of a stopped run: every consumer of the session's status treats
ABORTED, INTERRUPTED and FAILED alike as a run that ended without a verdict — the MQTT verdict
(ERROR, NotExecuting), the notification (ERROR), the CAN panel's lamp — and a run in any of
them no longer blocks the next start."""

from __future__ import annotations

import json

import pytest

from daemon.mqtt.config import MqttConfig
from daemon.mqtt.publisher import MachinePublisher
from daemon.notify.config import NotifyConfig
from daemon.notify.notifier import Notifier, RunWatcher
from daemon.run.phases import READY_STATES, STOPPED_STATES, State
from daemon.store.journal import Store
from drivers.can.panel import lamp_for


def _status(state: str, busy: bool) -> dict:
    return {"machine": "mill1", "state": state, "reason": f"r {state}", "run_id": "R1",
            "trigger": "hmi", "done": 3, "total": 140, "elapsed_s": 1.0, "eta_s": None,
            "verdict": None, "busy": busy, "link_ok": True}


def test_the_ready_states_are_idle_and_the_three_stopped_ones():
    assert set(READY_STATES) == {State.IDLE, *STOPPED_STATES}
    assert set(STOPPED_STATES) == {State.ABORTED, State.INTERRUPTED, State.FAILED}


@pytest.mark.parametrize("state", [str(s) for s in STOPPED_STATES])
async def test_a_stopped_run_is_an_error_for_mqtt_notifications_and_the_panel(tmp_path, state):
    store = Store(tmp_path / "j.sqlite")
    try:
        pub = MachinePublisher(MqttConfig(host="127.0.0.1", port=1883, site="p", root="rumba",
                                          username=None, password=None, tls=None, qos=1,
                                          keepalive_s=5, queue_max=100,
                                          health_interval_s=60.0), "mill1", store)
        sent: list = []
        notifier = Notifier(NotifyConfig(on=frozenset({"ERROR"}), deadlines={},
                                         days=frozenset()))
        notifier.notify = sent.append  # type: ignore[method-assign]
        watcher = RunWatcher(notifier, "mill1")
        for st in (_status("CAPTURE", True), _status(state, False)):
            pub.on_status(st)
            watcher.on_status(st)
        verdict = json.loads(pub.retained["rumba/p/mill1/verdict"])
        assert (verdict["status"], verdict["summary"]) == ("ERROR", f"r {state}")
        item = json.loads(pub.retained["rumba/p/mill1/state"])["machinery_item_state"]
        assert item == "NotExecuting"
        assert [(n.event, n.status) for n in sent] == [("verdict", "ERROR")]
        assert lamp_for(_status(state, False))[0] == "error"
    finally:
        store.close()


async def test_the_hmi_abort_names_a_scripts_signal_and_stops_only_its_run(tmp_path):
    """``rumba verify --daemon``'s abort: ``by`` only from a bearer script and only a known
    signal (the journal's text is fixed, never the client's), ``run_id`` only that run."""
    import aiohttp

    from benchmarks.rigs.daemon_helpers import thesis_rows, thesis_setup, write_daemon_yaml
    from daemon.analysis.replay_link import ReplayLink, prepare_from_rows
    from daemon.config import load_daemon_config
    from daemon.service.service import Service

    token = "t0k3n-for-tests-0123456789"
    rows = thesis_rows(thesis_setup())
    svc = Service(load_daemon_config(write_daemon_yaml(tmp_path, token=token)),
                  lambda s: ReplayLink(rows, s.machine, delay_s=0.01),
                  prepare=prepare_from_rows(rows))
    await svc.start()
    try:
        url = svc.hmi_url + "api/machines/mill1/abort"
        async with aiohttp.ClientSession(headers={"Authorization": f"Bearer {token}"}) as http:
            run_id = svc.trigger("mill1", "cli")
            for by in ("SIGKILL", "x\nFORGED", ""):
                r = await http.post(url, params={"by": by, "run_id": run_id})
                assert r.status == 400 and "by: expected one of SIGINT" in \
                    (await r.json())["error"]
            r = await http.post(url, params={"by": "SIGINT", "run_id": "20260101T000000Z-0"})
            assert r.status == 409 and "is not running" in (await r.json())["error"]
            assert svc.sessions["mill1"].busy  # another run's id stops nothing
            r = await http.post(url, params={"by": "SIGTERM", "run_id": run_id})
            st = await r.json()
            assert r.status == 200 and (st["run_id"], st["state"], st["busy"]) == (
                run_id, "ABORTED", False)
            assert st["reason"].startswith("aborted by SIGTERM on rumba verify --daemon during ")
            assert svc.store.run(run_id).state == "ABORTED"
            r = await http.post(url, params={"run_id": run_id})  # ended: nothing to stop
            assert r.status == 409
    finally:
        await svc.stop()
