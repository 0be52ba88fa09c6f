"""A controller that refuses the connection (nothing listens on the port) is reported at once on
the first connection, naming the refusal; a controller that does not answer is still waited for
``connect_timeout_s``; once a link has been connected, a refusal (a rebooting controller) is
retried like any other failure. Real drivers against real loopback sockets."""

from __future__ import annotations

import asyncio
import contextlib
import socket

import pytest

from benchmarks.rigs.transport_sim import make_truth
from drivers.base import LinkError
from drivers.modbus.link import ModbusLink
from drivers.modbus.schema import ModbusLinkConfig
from drivers.opcua.link import OpcUaLink
from drivers.opcua.schema import OpcUaLinkConfig
from simulators.controller import VirtualController
from simulators.frontends.modbus import ModbusFrontend

PATIENT_S = 600.0  # a connect timeout no test could wait for: only a fast refusal passes


def closed_port() -> int:
    """A loopback port nobody listens on (bound for a moment by us, then released)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def links(port: int, timeout_s: float) -> list:
    return [OpcUaLink(OpcUaLinkConfig(transport="opcua", url=f"opc.tcp://127.0.0.1:{port}",
                                      security="none", connect_timeout_s=timeout_s,
                                      request_timeout_s=0.5)),
            ModbusLink(ModbusLinkConfig(transport="modbus", port=port,
                                        connect_timeout_s=timeout_s, request_timeout_s=0.5))]


@pytest.mark.parametrize("kind", [0, 1], ids=["opcua", "modbus"])
async def test_refused_first_connection_fails_at_once_naming_it(kind):
    link = links(closed_port(), PATIENT_S)[kind]
    try:
        async with asyncio.timeout(60):  # generous: the old code waited PATIENT_S
            with pytest.raises(LinkError) as e:
                await link.connect()
    finally:
        await link.close()
    msg = str(e.value)
    assert "connection refused" in msg and "nothing listens there" in msg, msg
    assert "unreachable after" not in msg


async def test_silent_controller_is_still_waited_for():
    """A port that accepts but never answers the OPC UA hello: not a refusal, so the link
    retries until connect_timeout_s and says so."""
    server = await asyncio.start_server(lambda r, w: None, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    link = links(port, 1.0)[0]
    try:
        async with asyncio.timeout(60):
            with pytest.raises(LinkError, match=r"unreachable after 1 s"):
                await link.connect()
    finally:
        await link.close()
        server.close()
        with contextlib.suppress(Exception):
            await server.wait_closed()


async def test_refused_after_a_first_connection_is_retried():
    """The controller was there and reboots: its refusals are waited through (the session's
    reconnect keeps trying), not reported as a wrong address."""
    fe = ModbusFrontend(VirtualController(make_truth(), dialect="fanuc"))
    port = await fe.start()
    link = ModbusLink(ModbusLinkConfig(transport="modbus", port=port, connect_timeout_s=1.0,
                                       request_timeout_s=0.5))
    try:
        await link.connect()
        await link.close()
        await fe.stop()
        async with asyncio.timeout(60):
            with pytest.raises(LinkError, match=r"unreachable after 1 s") as e:
                await link.connect()
        assert "nothing listens there" not in str(e.value)
    finally:
        await link.close()
        await fe.stop()
