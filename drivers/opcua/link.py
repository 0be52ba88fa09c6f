"""OPC UA link (asyncua client): program transfer + start by method call, subscriptions to the
start request, the touch counter and the controller state, result ring reads, verdict write-back
with the request/busy/done handshake, certificate + user authentication, reconnect with backoff.
Every request is awaited through ``drivers.cancel.keep_cancel``: an abort's cancellation that
lands with a response is never lost.

Address space: contracts/opcua_space.py (table in drivers/README.md). No touch is lost when
notifications coalesce or the connection drops: on every wake-up the counter is read and every
slot between the last seen and the current counter is read (ring of 32).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import time
from collections.abc import AsyncIterator
from typing import Any

from asyncua import Client, ua

from contracts.jobs import ProgramJob, Verdict
from contracts.messages import ProbeHit
from contracts.opcua_space import BY_ROLE, RESULT_ROLES, RING_SLOTS, node_id
from contracts.temperatures import TemperatureChannel
from drivers.base import (
    Capabilities,
    ChannelMissing,
    CncLink,
    LinkError,
    StartRequest,
)
from drivers.cancel import keep_cancel
from drivers.hits import HitFactory, MalformedResult
from drivers.opcua.reasons import MISSING_NODE, quiet_connection_loss, why
from drivers.opcua.ring import _number, check_counter, ring_hit
from drivers.opcua.schema import OpcUaLinkConfig
from drivers.opcua_client import secure_client
from drivers.result_ring import ResultRingReader, RingPoll
from drivers.retry import Refused, wait_event, with_backoff

logging.getLogger("asyncua").setLevel(logging.ERROR)
log = logging.getLogger("rumba.opcua")
quiet_connection_loss()

SUBSCRIBED = ("request", "touch_counter", "state")
NODE_ROLES = tuple(BY_ROLE)
"""Roles whose node id may be overridden in the link config (``nodes: {role: id}``)."""
POLL_S = 0.5  # fallback re-read when no notification arrives (a lost publish, a reconnect)


class _Fatal(Exception):
    """A connect failure retrying cannot fix (bad password, untrusted certificate)."""


class _Notify:
    def __init__(self, event: asyncio.Event) -> None:
        self.event = event

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        self.event.set()

    def status_change_notification(self, status: Any) -> None:
        self.event.set()


def _double(value: float) -> ua.DataValue:
    return ua.DataValue(ua.Variant(float(value), ua.VariantType.Double))


class OpcUaLink(ResultRingReader, CncLink):
    ring_slots = RING_SLOTS
    capabilities = Capabilities(start_request=True, streams_blocks=False, loads_program=True,
                                writes_verdict=True, can_abort=True)

    def __init__(self, cfg: OpcUaLinkConfig) -> None:
        unknown = set(cfg.nodes) - set(NODE_ROLES)
        if unknown:
            raise LinkError(f"opcua nodes: unknown role(s) {sorted(unknown)} "
                            f"(known: {', '.join(NODE_ROLES)})")
        self.cfg = cfg
        self._client: Client | None = None
        self._n: dict[str, Any] = {}
        self._wake = asyncio.Event()
        self._sub: Any = None
        self._connected_once = False

    # ------------------------------------------------------------------ connection

    async def _connect_once(self) -> Client:
        cfg = self.cfg
        try:
            client = await secure_client(cfg)
        except (OSError, ValueError) as e:
            raise _Fatal(f"opcua {cfg.url}: security setup: {e}") from None
        try:
            await client.connect(auto_reconnect=True, reconnect_max_delay=10.0,
                                 reconnect_request_timeout=cfg.request_timeout_s)
        except ua.UaError as e:  # status codes (bad password, untrusted) and policy mismatch
            with contextlib.suppress(Exception):
                await client.disconnect()
            raise _Fatal(f"opcua {cfg.url}: rejected: {type(e).__name__} ({e})") from None
        except (TimeoutError, OSError, ConnectionError) as e:
            with contextlib.suppress(Exception):
                await client.disconnect()
            error = Refused if isinstance(e, ConnectionRefusedError) else LinkError
            raise error(str(e) or type(e).__name__) from None
        return client

    async def connect(self) -> None:
        if self._client is not None:
            return
        try:
            # refused fails at once only before the first success (start-up, rumba verify)
            client = await with_backoff(self._connect_once, what=f"opcua {self.cfg.url}",
                                        timeout_s=self.cfg.connect_timeout_s,
                                        refused_is_final=not self._connected_once)
        except _Fatal as e:
            raise LinkError(str(e)) from None
        try:
            ns = 0
            if len(self.cfg.nodes) < len(NODE_ROLES):
                ns = await client.get_namespace_index(self.cfg.namespace_uri)
            self._ns = ns  # temperature channels given as a /path live in this namespace
            self._n = {r: client.get_node(node_id(r, ns, self.cfg.nodes)) for r in NODE_ROLES}
            for role in NODE_ROLES:  # every node must exist: a typo fails now, not mid-run
                if BY_ROLE[role].kind != "Method":
                    try:
                        await self._n[role].read_value()
                    except ua.UaStatusCodeError as e:
                        raise ValueError(f"{role} = {node_id(role, ns, self.cfg.nodes)}: "
                                         f"{type(e).__name__}") from None
            self._sub = await client.create_subscription(50, _Notify(self._wake))
            await self._sub.subscribe_data_change([self._n[r] for r in SUBSCRIBED])
        except (ua.UaError, ValueError, OSError, ConnectionError) as e:
            with contextlib.suppress(Exception):
                await client.disconnect()
            raise LinkError(f"opcua {self.cfg.url}: address space: {e}") from None
        self._client = client
        self._connected_once = True

    async def _read(self, roles: tuple[str, ...]) -> list[Any]:
        if self._client is None:
            raise LinkError(f"opcua {self.cfg.url}: not connected")
        try:
            return await keep_cancel(self._client.read_values([self._n[r] for r in roles]))
        except (TimeoutError, ua.UaError, OSError, ConnectionError) as e:
            raise LinkError(f"opcua {self.cfg.url}: read {', '.join(roles)}: "
                            f"{why(e, self.cfg.request_timeout_s)}") from None

    async def _read_during_run(self, roles: tuple[str, ...]) -> list[Any]:
        """A read that rides out a connection drop: asyncua reconnects in the background and
        the results wait in the ring (the CNC holds while it is full), so retry until
        ``connect_timeout_s`` has passed without success."""
        deadline = time.monotonic() + self.cfg.connect_timeout_s
        while True:
            try:
                return await self._read(roles)
            except LinkError:
                if time.monotonic() > deadline:
                    raise
                await asyncio.sleep(0.2)

    async def read_temperature(self, channel: TemperatureChannel) -> float:
        if self._client is None:
            raise LinkError(f"opcua {self.cfg.url}: not connected")
        nid = (channel.address if channel.address.startswith("ns=")
               else f"ns={getattr(self, '_ns', 0)};s={channel.address}")
        try:
            value = await keep_cancel(self._client.get_node(nid).read_value())
        except ua.UaStatusCodeError as e:
            if e.code in MISSING_NODE:
                raise ChannelMissing(f"opcua {self.cfg.url}: temperature {channel.name} "
                                     f"({nid}): no such node on the controller "
                                     f"({ua.StatusCode(e.code).name})") from None
            raise LinkError(f"opcua {self.cfg.url}: temperature {channel.name} ({nid}): "
                            f"{why(e, self.cfg.request_timeout_s)}") from None
        except ValueError:  # not a node id at all
            raise ChannelMissing(f"opcua {self.cfg.url}: temperature {channel.name}: "
                                 f"{nid!r} is not a node id") from None
        except (TimeoutError, ua.UaError, OSError, ConnectionError) as e:
            raise LinkError(f"opcua {self.cfg.url}: temperature {channel.name} ({nid}): "
                            f"{why(e, self.cfg.request_timeout_s)}") from None
        if (not isinstance(value, int | float) or isinstance(value, bool)
                or not math.isfinite(value)):
            raise LinkError(f"opcua {self.cfg.url}: temperature {channel.name} ({nid}) = "
                            f"{value!r}, not a finite number")
        return float(value) * channel.scale + channel.offset_c

    async def _write(self, role: str, value: float) -> None:
        try:
            await keep_cancel(self._n[role].write_value(_double(value)))
        except (TimeoutError, ua.UaError, OSError, ConnectionError) as e:
            raise LinkError(f"opcua {self.cfg.url}: write {role}: "
                            f"{why(e, self.cfg.request_timeout_s)}") from None

    async def _call(self, role: str, *args: ua.Variant) -> None:
        try:
            await keep_cancel(self._n["methods"].call_method(self._n[role], *args))
        except (TimeoutError, ua.UaError, OSError, ConnectionError) as e:
            raise LinkError(f"opcua {self.cfg.url}: {BY_ROLE[role].path} refused: "
                            f"{why(e, self.cfg.request_timeout_s)}") from None

    async def _sleep_for_change(self, timeout_s: float) -> None:
        self._wake.clear()
        await wait_event(self._wake, timeout_s)

    # ------------------------------------------------------------------ handshake

    async def wait_start_request(self) -> StartRequest:
        """Wait for REQUEST=1 with DONE=0; answer BUSY=1. DONE is cleared once REQUEST drops."""
        while True:
            request, done = await self._read_handshake()
            if done >= 0.5 and request < 0.5:
                await self._write("done", 0.0)
                await self._write("verdict", 0.0)
                done = 0.0
            if request >= 0.5 and done < 0.5:
                await self._write("busy", 1.0)
                return StartRequest(source="cnc", detail=f"{BY_ROLE['request'].path} = 1")
            await self._sleep_for_change(POLL_S)

    async def _read_handshake(self) -> tuple[float, float]:
        # While the connection is down asyncua reconnects with backoff in the background;
        # waiting for a start request keeps trying until it is back. When that has not
        # brought the session back within connect_timeout_s, start over with a new client:
        # after a controller restart with security on, asyncua 2.1's reconnect can stay stuck
        # (the server refuses every request with a bad signature) — seen in CI-load tests.
        failing_since: float | None = None
        while True:
            try:
                request, done = await self._read(("request", "done"))
                return float(request), float(done)
            except LinkError as e:
                now = time.monotonic()
                failing_since = now if failing_since is None else failing_since
                if self._client is None or now - failing_since > self.cfg.connect_timeout_s:
                    log.warning("%s; no answer for %.0f s: reconnecting with a new session",
                                e, now - failing_since)
                    await self._fresh_session()
                    failing_since = None
                    continue
                await asyncio.sleep(POLL_S)

    async def _fresh_session(self) -> None:
        """Drop the client (and its background reconnect) and connect anew; on failure the
        caller keeps waiting and tries again later."""
        old, self._client = self._client, None
        if old is not None:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(old.disconnect(), 2.0)
        try:
            await self.connect()
        except LinkError as e:
            log.warning("%s", e)
            await asyncio.sleep(POLL_S)

    async def write_verdict(self, verdict: Verdict) -> None:
        await self._write("verdict", float(verdict.code))
        await self._write("done", 1.0)
        await self._write("busy", 0.0)

    # ------------------------------------------------------------------ program

    async def run(self, job: ProgramJob) -> AsyncIterator[ProbeHit]:
        if self._client is None:
            raise LinkError("opcua link not connected")
        await self._call("load_program", ua.Variant(job.text, ua.VariantType.String),
                         ua.Variant(job.dialect, ua.VariantType.String),
                         ua.Variant(json.dumps(job.files) if job.files else "",
                                    ua.VariantType.String))
        (last,) = await self._read(("touch_counter",))
        last = int(_number(last, "touch_counter", "after LoadProgram", integer=True))
        high = last + job.touch_count if job.touch_count else None
        self._hits, self._last, self._high = HitFactory(job), last, high
        await self._call("start")
        async for hit in self._ring_results(job):
            yield hit

    # ------------------------------------------------------------------ the ring's reads

    async def _poll_ring(self, job: ProgramJob, got: int) -> RingPoll:
        counter, state, alarm = await self._read_during_run(("touch_counter", "state",
                                                             "alarm"))
        try:
            counter = check_counter(counter, state, self._last, self._high)
        except MalformedResult:
            await self._abort_quietly()
            raise
        return RingPoll(counter - self._last, state, alarm)

    async def _read_results(self, new: int) -> AsyncIterator[ProbeHit]:
        rows = await self._read_during_run(RESULT_ROLES)
        for n in range(self._last + 1, self._last + new + 1):
            try:
                hit = ring_hit(self._hits, rows, n)
            except MalformedResult:
                await self._abort_quietly()
                raise
            self._last = n
            yield hit

    async def _acknowledge(self) -> None:
        with contextlib.suppress(LinkError):  # re-sent with the next batch anyway
            await self._write("touch_ack", float(self._last))  # frees the slots for the CNC

    async def _alarm_message(self, poll: RingPoll) -> str:
        return f"controller alarm: {poll.alarm or 'unknown'}"

    def _result_timeout_s(self) -> float:
        return self.cfg.result_timeout_s

    def _timeout_message(self, poll: RingPoll, got: int, job: ProgramJob) -> str:
        return (f"no touch result for {self.cfg.result_timeout_s:g} s (state {poll.state}, "
                f"{got} of {job.touch_count} touches)")

    async def _wait(self, progressed: bool) -> None:
        await self._sleep_for_change(POLL_S)

    async def abort(self) -> None:
        if self._client is None:  # never "done" silently: the program may still run there
            raise LinkError("opcua link not connected: the controller was not reset")
        await self._call("abort")

    async def _abort_quietly(self) -> None:
        """Stop a program whose results are garbage (the connection itself works)."""
        with contextlib.suppress(LinkError):
            await self.abort()

    async def close(self) -> None:
        client, self._client = self._client, None
        if client is not None:
            with contextlib.suppress(Exception):
                await client.disconnect()
