"""systemd's notification protocol, on real AF_UNIX datagram sockets: the message format for a
path and an abstract socket, and `rumba run` as a subprocess (against the simulated CNC over
OPC UA) sending READY=1 once serving, WATCHDOG=1 again and again, STOPPING=1 on SIGTERM."""

from __future__ import annotations

import asyncio
import os
import secrets
import signal
import socket
import sys

from benchmarks.rigs.daemon_helpers import CONFIG, ROOT, write_daemon_yaml
from daemon.service import sdnotify


def dgram_socket(address: str) -> socket.socket:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.bind(address)
    s.settimeout(10)
    return s


def test_notify_to_a_path_and_an_abstract_socket(tmp_path):
    path = str(tmp_path / "notify.sock")
    with dgram_socket(path) as s:
        assert sdnotify.notify("READY=1\nSTATUS=serving", {"NOTIFY_SOCKET": path})
        assert s.recv(4096) == b"READY=1\nSTATUS=serving"
    name = f"rumba-test-{secrets.token_hex(6)}"
    with dgram_socket("\0" + name) as s:
        assert sdnotify.notify("WATCHDOG=1", {"NOTIFY_SOCKET": "@" + name})
        assert s.recv(4096) == b"WATCHDOG=1"
    # not under systemd, or its socket gone: nothing sent, nothing raised
    assert not sdnotify.notify("READY=1", {})
    assert not sdnotify.notify("READY=1", {"NOTIFY_SOCKET": str(tmp_path / "gone.sock")})


def test_watchdog_interval_is_half_the_timeout_for_this_process_only():
    me = str(os.getpid())
    assert sdnotify.watchdog_interval_s({"WATCHDOG_USEC": "30000000"}) == 15.0
    assert sdnotify.watchdog_interval_s({"WATCHDOG_USEC": "30000000", "WATCHDOG_PID": me}) == 15
    assert sdnotify.watchdog_interval_s({"WATCHDOG_USEC": "30000000", "WATCHDOG_PID": "1"}) is None
    assert sdnotify.watchdog_interval_s({"WATCHDOG_USEC": "0"}) is None
    assert sdnotify.watchdog_interval_s({"WATCHDOG_USEC": "soon"}) is None
    assert sdnotify.watchdog_interval_s({}) is None


async def test_rumba_run_notifies_ready_watchdog_and_stopping(tmp_path):
    from simulators.controller import VirtualController
    from simulators.frontends.opcua import OpcUaFrontend
    from simulators.truth import TruthModel

    truth = TruthModel.from_files(CONFIG / "machines/thesis_wcbxfzyt.yaml",
                                  CONFIG / "artefacts/thesis_4ball.yaml")
    sim = OpcUaFrontend(VirtualController(truth, dialect="fanuc"), security="none")
    url = await sim.start()
    cfg = write_daemon_yaml(tmp_path, link=f"{{transport: opcua, url: '{url}', security: none}}")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(tmp_path / "notify.sock"))
    sock.setblocking(False)
    env = {**os.environ, "NOTIFY_SOCKET": str(tmp_path / "notify.sock"),
           "WATCHDOG_USEC": "200000"}  # a ping every 0.1 s
    env.pop("WATCHDOG_PID", None)
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "daemon.cli", "run", "--config", str(cfg), cwd=ROOT, env=env,
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.DEVNULL)
    loop = asyncio.get_running_loop()
    got: list[str] = []

    async def until(pred) -> None:
        async with asyncio.timeout(60):  # generous: start-up imports and connects first
            while not pred():
                got.append((await loop.sock_recv(sock, 4096)).decode())

    try:
        await until(lambda: any(m.startswith("READY=1") for m in got))
        ready = next(m for m in got if m.startswith("READY=1"))
        assert "STATUS=serving mill1 (opcua, fanuc)" in ready
        # the banner (HMI listening) was printed before READY=1 was sent
        async with asyncio.timeout(10):
            banner = [await proc.stdout.readline() for _ in range(2)]
        assert banner[1].startswith(b"rumba: HMI at http://127.0.0.1:"), banner
        n = len(got)
        await until(lambda: got[n:].count("WATCHDOG=1") >= 5)
        assert not any(m.startswith("STOPPING=1") for m in got)
        proc.send_signal(signal.SIGTERM)
        await until(lambda: any(m.startswith("STOPPING=1") for m in got))
        async with asyncio.timeout(60):
            assert await proc.wait() == 0
        assert got.index(ready) < got.index("WATCHDOG=1")  # pings start once ready
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
        sock.close()
        await sim.stop()
