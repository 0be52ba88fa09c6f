"""Live results out on MQTT (aiomqtt): each machine's state, verdict, identified links and
health under ``<root>/<site>/<machine>/…``, JSON with units in the key names.

Topic tree (documented in README "Fleet"; retained = the broker keeps the last one for late
subscribers):

    rumba/<site>/<machine>/online    retained  {"online": bool, "time_unix_s"}  (will: false)
    rumba/<site>/<machine>/state     retained  every state change (+ OPC 40001 item state)
    rumba/<site>/<machine>/progress            touches done / total during a run (QoS 0)
    rumba/<site>/<machine>/verdict   retained  the last verdict (ABORTED/INTERRUPTED/FAILED → ERROR)
    rumba/<site>/<machine>/links     retained  identified ISO 230-1 link errors, µm / µrad
    rumba/<site>/<machine>/health    retained  measurement health and daemon figures

A broker outage never blocks or fails a run: the session's listener only appends to a bounded
queue (drop-oldest, counted in ``dropped``); one background task per machine connects,
reconnects with backoff and publishes; retained topics are re-sent on every reconnect, so a
dropped state or verdict is repaired as soon as the broker is back.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import time
from collections import deque
from collections.abc import Callable
from pathlib import PurePath
from typing import Any

import aiomqtt

from daemon.analysis.figures import figures_json, run_figures
from daemon.analysis.judge import volumetric_max_um
from daemon.analysis.result import Analysis
from daemon.mqtt.config import MqttConfig
from daemon.store.journal import Store

log = logging.getLogger("rumba.mqtt")

BACKOFF_S = (0.5, 1.0, 2.0, 5.0, 10.0, 30.0)
# OPC 40001-1 (umati machinery) MachineryItemState for a verification cell
_ITEM_STATE = {"IDLE": "NotExecuting", "ABORTED": "NotExecuting",
               "INTERRUPTED": "NotExecuting", "FAILED": "NotExecuting"}
_ENDED = tuple(_ITEM_STATE)  # a session in one of these runs nothing (run/phases READY_STATES)


def link_payload(analysis: Analysis) -> dict[str, Any]:
    """{"EX0Q": {"value_um": …, "std_um": …}, "EB0Q": {"value_urad": …}}: unit in the key."""
    out: dict[str, Any] = {}
    for name, e in analysis.links.items():
        u = e.unit or ("urad" if name[1:2] in "ABC" else "um")
        out[name] = {f"value_{u}": e.value, f"std_{u}": e.std}
    return out


def health_payload(analysis: Analysis) -> dict[str, Any]:
    radius = [abs(h.radius_dev_um) for h in analysis.health if h.radius_dev_um is not None]
    form = [h.form_rms_um for h in analysis.health if h.form_rms_um is not None]
    return {"residual_rms_um": analysis.residual_rms_um,
            "condition_number": analysis.condition_number,
            "volumetric_max_um": volumetric_max_um(analysis),
            "sphere_radius_dev_max_um": max(radius) if radius else None,
            "sphere_form_rms_max_um": max(form) if form else None,
            "stability_max_shift_um": analysis.stability.max_shift_um
            if analysis.stability else None,
            # the figures as the report shows them (rounded, name, unit, definition);
            # volumetric_max_um above stays as it was for existing subscribers
            "figures": figures_json(run_figures(analysis))}


class MachinePublisher:
    """The MQTT client of one machine (its own will: ``online`` false when the daemon dies)."""

    def __init__(self, cfg: MqttConfig, machine: str, store: Store,
                 extra_health: Callable[[], dict[str, Any]] | None = None) -> None:
        self.cfg, self.machine, self.store = cfg, machine, store
        self.prefix = f"{cfg.root}/{cfg.site}/{machine}"
        self.queue: deque[tuple[str, bytes, int, bool]] = deque()
        self.retained: dict[str, bytes] = {}
        self.dropped = 0
        self.published = 0
        self.connected = False
        self.last_error = ""
        self.extra_health = extra_health
        self._ready = asyncio.Event()
        self._task: asyncio.Task | None = None
        self._last_state: tuple | None = None
        self._run_health: dict[str, Any] = {}
        self._told: tuple | None = None  # (run, report_state) the verdict was last sent with

    # ------------------------------------------------------------------------- enqueueing
    def publish(self, leaf: str, payload: dict[str, Any], *, retain: bool = False,
                qos: int | None = None) -> None:
        """Queue a message (never blocks, never raises for the broker's sake)."""
        topic = f"{self.prefix}/{leaf}"
        body = json.dumps({**payload, "time_unix_s": round(time.time(), 3)},
                          allow_nan=False, default=str).encode()
        if retain:
            self.retained[topic] = body
        if len(self.queue) >= self.cfg.queue_max:
            self.queue.popleft()
            self.dropped += 1
        self.queue.append((topic, body, self.cfg.qos if qos is None else qos, retain))
        self._ready.set()

    def on_status(self, st: dict[str, Any]) -> None:
        """The session's listener: state changes, progress, and at the end of a run its
        verdict, links and health (read from the local journal, which has them by then)."""
        key = (st["state"], st["run_id"], st["reason"], st["link_ok"])
        if key != self._last_state:
            previous, self._last_state = self._last_state, key
            item = "NotAvailable" if not st["link_ok"] else _ITEM_STATE.get(st["state"],
                                                                             "Executing")
            self.publish("state", {
                "state": st["state"], "run_id": st["run_id"], "trigger": st["trigger"],
                "reason": st["reason"], "machinery_item_state": item,
                "link_ok": st["link_ok"], "done_touches": st["done"],
                "total_touches": st["total"]}, retain=True)
            ended = previous is not None and previous[0] not in _ENDED
            if st["run_id"] and ended and st["state"] in _ENDED:
                self._run_end(st)
        elif st["state"] == "CAPTURE":
            self.publish("progress", {"run_id": st["run_id"], "done_touches": st["done"],
                                      "total_touches": st["total"], "eta_s": st["eta_s"]},
                         qos=0)
        if st["state"] == "IDLE" and st["run_id"]:
            self._report_end(st)

    def _report_end(self, st: dict[str, Any]) -> None:
        """The report is written after the run's end; the retained verdict is
        published again once it is written (its file name) or failed (report_state)."""
        v = st.get("verdict") or {}
        told = (st["run_id"], v.get("report_state"))
        if st["state"] == "IDLE" and told[1] in ("written", "failed") and told != self._told:
            self._told = told
            self._verdict(st)

    def _run_end(self, st: dict[str, Any]) -> None:
        if st.get("job") == "map" and st["state"] == "IDLE":
            return  # a map done leaves the machine's retained verdict (the last check's)
        run_id = st["run_id"]
        ok = self._verdict(st)
        analysis = self.store.analysis(run_id) if ok else None
        if analysis is not None:
            self.publish("links", {"run_id": run_id, "links": link_payload(analysis)},
                         retain=True)
            self._run_health = {"run_id": run_id, **health_payload(analysis)}
        self.publish_health()

    def _verdict(self, st: dict[str, Any]) -> bool:
        """The retained verdict message of the run ``st`` ended; whether it ended DONE."""
        run_id = st["run_id"]
        v = st.get("verdict") or {}
        ok = st["state"] == "IDLE" and v.get("status")
        self.publish("verdict", {
            "run_id": run_id, "status": v["status"] if ok else "ERROR",
            "summary": v.get("summary", "") if ok else st["reason"],
            "reasons": v.get("reasons", []) if ok else [st["reason"]],
            # the file name only: a path on the daemon's PC means nothing to a subscriber
            # elsewhere and would tell the network how the shop PC is laid out
            "report": PurePath(v["report"]).name if v.get("report") else None,
            "run_state": "DONE" if st["state"] == "IDLE" else st["state"],
            # "writing" at the run's end, then "written" (report set) or "failed"
            "report_state": v.get("report_state") if ok else None,
            "elapsed_s": st["elapsed_s"]}, retain=True)
        return bool(ok)

    def publish_health(self) -> None:
        extra = {}
        if self.extra_health is not None:
            with contextlib.suppress(Exception):
                extra = self.extra_health()
        self.publish("health", {**self._run_health, **extra,
                                "mqtt_dropped_messages": self.dropped}, retain=True)

    # --------------------------------------------------------------------------- sending
    def start(self) -> None:
        self._task = asyncio.get_running_loop().create_task(self._forever(),
                                                            name=f"mqtt-{self.machine}")

    async def stop(self, flush_timeout_s: float = 2.0) -> None:
        """Publish what is queued if the broker answers within the timeout, then leave."""
        self.publish("online", {"online": False}, retain=True)  # a clean exit, not the will
        deadline = time.monotonic() + flush_timeout_s
        while self.queue and self.connected and time.monotonic() < deadline:
            await asyncio.sleep(0.02)
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(BaseException):
                await self._task

    async def _forever(self) -> None:
        failures = 0
        cfg = self.cfg
        will = aiomqtt.Will(f"{self.prefix}/online", json.dumps({"online": False}), 1, True)
        while True:
            try:
                async with aiomqtt.Client(
                        cfg.host, cfg.port, username=cfg.username, password=cfg.password,
                        tls_context=cfg.tls, keepalive=cfg.keepalive_s, will=will,
                        identifier=f"rumba-{cfg.site}-{self.machine}",
                        timeout=min(10, cfg.keepalive_s)) as client:
                    self.connected, failures = True, 0
                    if self.last_error:
                        log.info("%s: MQTT broker %s:%d back", self.machine, cfg.host, cfg.port)
                    self.last_error = ""
                    await client.publish(f"{self.prefix}/online", json.dumps(
                        {"online": True, "time_unix_s": round(time.time(), 3)}), 1, True)
                    queued = {(t, b) for t, b, _, _ in self.queue}
                    for topic, body in list(self.retained.items()):  # repair what was dropped
                        if (topic, body) not in queued:  # (what is queued goes out in order)
                            await client.publish(topic, body, cfg.qos, True)
                    await self._send(client)
            except aiomqtt.MqttError as e:
                msg = str(e) or type(e).__name__
                if msg != self.last_error:
                    log.warning("%s: MQTT broker %s:%d: %s (queueing, %d dropped so far)",
                                self.machine, cfg.host, cfg.port, msg, self.dropped)
                self.last_error = msg
            self.connected = False
            await asyncio.sleep(BACKOFF_S[min(failures, len(BACKOFF_S) - 1)])
            failures += 1

    async def _send(self, client: aiomqtt.Client) -> None:
        while True:
            if not self.queue:
                self._ready.clear()
                await self._ready.wait()
                continue
            topic, body, qos, retain = self.queue[0]  # in order: every state change goes out
            await client.publish(topic, body, qos, retain)  # QoS 1 waits for PUBACK
            self.queue.popleft()
            self.published += 1
