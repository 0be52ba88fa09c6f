"""`rumba sim --serve` with stdin that the event loop cannot watch (`< /dev/null`, as under a
service manager, or a file of commands): no asyncio traceback, the simulator keeps serving, and
the commands in a file are obeyed. Real subprocess, real Modbus TCP client."""

from __future__ import annotations

import asyncio
import signal
import subprocess
import sys

from benchmarks.rigs.daemon_helpers import CONFIG
from drivers.modbus.link import ModbusLink
from drivers.modbus.schema import ModbusLinkConfig

SIM = [sys.executable, "-m", "daemon.cli", "sim",
       "--machine", str(CONFIG / "machines/thesis_wcbxfzyt.yaml"),
       "--artefact", str(CONFIG / "artefacts/thesis_4ball.yaml"), "--serve", "modbus"]


async def _listening(proc: asyncio.subprocess.Process) -> int:
    async with asyncio.timeout(60):
        line = (await proc.stdout.readline()).decode()
    assert line.startswith("listening: modbus-tcp://127.0.0.1:"), line
    return int(line.split()[1].rsplit(":", 1)[1])


async def test_stdin_dev_null_keeps_serving_without_traceback(tmp_path):
    proc = await asyncio.create_subprocess_exec(
        *SIM, cwd=tmp_path, stdin=subprocess.DEVNULL, stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE)
    try:
        port = await _listening(proc)
        link = ModbusLink(ModbusLinkConfig(transport="modbus", port=port, connect_timeout_s=10))
        try:
            await link.connect()  # reads the register map's id: the simulator answers
        finally:
            await link.close()
        proc.send_signal(signal.SIGTERM)
        async with asyncio.timeout(60):
            err = (await proc.stderr.read()).decode()
            assert await proc.wait() == 0
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
    assert "Traceback" not in err and "Exception in callback" not in err, err


def test_commands_from_a_file_are_obeyed(tmp_path):
    cmds = tmp_path / "commands.txt"
    cmds.write_text("request\nquit\n")
    with cmds.open("rb") as stdin:
        p = subprocess.run(SIM, cwd=tmp_path, stdin=stdin, capture_output=True, text=True,
                           timeout=60)
    assert p.returncode == 0, p.stderr
    assert "start-of-shift request raised" in p.stdout
    assert "Traceback" not in p.stderr, p.stderr


def test_run_at_the_console_loads_and_starts_the_newest_program(tmp_path):
    """``run FILE``: the operator runs a program at the control (a confirmed compensation);
    a pattern picks the newest file; without the control's dialect it is refused, not guessed."""
    import os

    old, new = tmp_path / "compensation_a.mpf", tmp_path / "compensation_b.mpf"
    old.write_text("this is not SINUMERIK\nM30\n")
    new.write_text("$TC_CARR15[1]=-0.038056\n$TC_CARR18[1]=0.038056\nM30\n")
    os.utime(old, (1, 1))
    cmds = tmp_path / "commands.txt"
    cmds.write_text(f"run {tmp_path}/compensation_*.mpf\nrun {tmp_path}/nothing_*.mpf\nquit\n")
    with cmds.open("rb") as stdin:
        p = subprocess.run([*SIM, "--dialect", "siemens"], cwd=tmp_path, stdin=stdin,
                           capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    assert "ran compensation_b.mpf: done" in p.stdout
    assert f"run: no file matches {tmp_path}/nothing_*.mpf" in p.stdout
    with cmds.open("rb") as stdin:
        p = subprocess.run(SIM, cwd=tmp_path, stdin=stdin, capture_output=True, text=True,
                           timeout=60)
    assert "run: the control's dialect is not known: start rumba sim with --dialect" in p.stdout
    assert "Traceback" not in p.stderr, p.stderr


async def test_serial_with_a_port_serves_tcp_and_the_sender_keeps_the_line(tmp_path):
    """``--serve serial --port``: one endpoint, raw TCP (a converter's socket://), and a sender
    that connects keeps the line: the start-of-shift request typed at the console reaches it
    (a pty opened beside it used to hold the port, and a TCP sender was closed at once)."""
    proc = await asyncio.create_subprocess_exec(
        *SIM[:-1], "serial", "--port", "0", cwd=tmp_path, stdin=asyncio.subprocess.PIPE,
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
    try:
        async with asyncio.timeout(60):
            line = (await proc.stdout.readline()).decode()
        assert line.startswith("listening: socket://127.0.0.1:"), line
        reader, writer = await asyncio.open_connection(
            "127.0.0.1", int(line.strip().rsplit(":", 1)[1]))
        try:
            async with asyncio.timeout(60):
                assert (await proc.stdout.readline()).startswith(b"serial: ")
                proc.stdin.write(b"request\n")
                await proc.stdin.drain()
                got = await reader.readline()
            assert got.strip().startswith(b"RUMBA REQUEST "), got
        finally:
            writer.close()
        proc.send_signal(signal.SIGTERM)
        async with asyncio.timeout(60):
            await proc.wait()
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
