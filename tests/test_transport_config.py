"""Link configuration and the registry (one clear error per bad key), and ``rumba sim --serve``
as a separate process that a link reaches over loopback."""

from __future__ import annotations

import asyncio
import sys
from pathlib import Path

import pytest

from contracts.yaml_files import ConfigError
from drivers.base import LinkError
from drivers.modbus.link import ModbusLink
from drivers.modbus.schema import ModbusLinkConfig
from drivers.opcua.link import OpcUaLink
from drivers.registry import link_config, make_link
from drivers.serial.link import SerialDncLink

ROOT = Path(__file__).resolve().parents[1]


def test_make_link_builds_each_transport():
    assert isinstance(make_link({"transport": "serial", "url": "/dev/ttyS0"}), SerialDncLink)
    assert isinstance(make_link({"transport": "modbus", "port": 5020}), ModbusLink)
    assert isinstance(make_link({"transport": "opcua", "url": "opc.tcp://127.0.0.1:4840/",
                                 "security": "none"}), OpcUaLink)


@pytest.mark.parametrize(("data", "message"), [
    ({"transport": "modbus", "prot": 502}, r"link: prot: unknown key"),
    ({"transport": "carrier-pigeon"}, r"transport: expected one of"),
    ({"transport": "serial", "url": "/dev/ttyS0", "framing": "9X9"}, r"link: framing:"),
    ({"transport": "serial", "url": "/dev/ttyS0", "baudrate": "fast"}, r"link: baudrate:"),
    ({"transport": "opcua", "url": "opc.tcp://h:4840/"}, r"needs 'certificate' and 'private_key'"),
    ({"transport": "opcua", "url": "http://h/", "security": "none"}, r"link: url:"),
    ({"transport": "opcua", "url": "opc.tcp://h:4840/", "security": "none",
      "user": {"name": "u"}}, r"exactly one of 'password' or 'password_env'"),
])
def test_bad_link_config_is_one_clear_error(data, message):
    with pytest.raises(ConfigError, match=message):
        link_config(data)


async def test_unset_password_env_is_a_clear_error(monkeypatch):
    monkeypatch.delenv("RUMBA_TEST_NO_SUCH_PW", raising=False)
    link = make_link({"transport": "opcua", "url": "opc.tcp://127.0.0.1:1/", "security": "none",
                      "user": {"name": "u", "password_env": "RUMBA_TEST_NO_SUCH_PW"}})
    with pytest.raises(LinkError, match="RUMBA_TEST_NO_SUCH_PW"):
        await link.connect()


async def test_unknown_opcua_node_role_is_refused():
    with pytest.raises(LinkError, match="unknown role"):
        make_link({"transport": "opcua", "url": "opc.tcp://h:1/", "security": "none",
                   "nodes": {"reqest": "ns=2;s=x"}})


async def test_rumba_sim_serve_modbus_process():
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "daemon.cli", "sim",
        "--machine", str(ROOT / "config/machines/thesis_wcbxfzyt.yaml"),
        "--artefact", str(ROOT / "config/artefacts/thesis_4ball.yaml"), "--serve", "modbus",
        stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE, cwd=ROOT)
    link = None
    try:
        assert proc.stdout is not None and proc.stdin is not None
        line = (await asyncio.wait_for(proc.stdout.readline(), 60)).decode()
        assert line.startswith("listening: modbus-tcp://127.0.0.1:"), line
        port = int(line.split(":")[-1].split()[0])
        link = ModbusLink(ModbusLinkConfig(transport="modbus", port=port))
        await link.connect()  # checks MAP_ID / MAP_VERSION
        proc.stdin.write(b"request\n")  # the CNC raises its start-of-shift request
        await proc.stdin.drain()
        req = await asyncio.wait_for(link.wait_start_request(), 10)
        assert req.source == "cnc"
        proc.stdin.write(b"quit\n")
        await proc.stdin.drain()
        assert await asyncio.wait_for(proc.wait(), 20) == 0
    finally:
        if link is not None:
            await link.close()
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
