"""`rumba sim --serve` with stdin that the event loop cannot watch (`< /dev/null`, as under a
service manager, or a file of commands): no asyncio traceback, the simulator keeps serving, and
the commands in a file are obeyed. Real subprocess, real Modbus TCP client."""

from __future__ import annotations

import asyncio
import signal
import subprocess
import sys

from drivers.modbus.link import ModbusLink
from drivers.modbus.schema import ModbusLinkConfig
from tests.daemon_helpers import CONFIG

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
