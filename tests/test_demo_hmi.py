"""`make demo-hmi`: the simulated CNC, the daemon and its HMI come up, the
printed one-time login signs in (an engineer account made for this session, the URL printed),
and Ctrl-C (SIGINT) stops everything: the daemon process is gone and the demo exits 0."""

from __future__ import annotations

import asyncio
import os
import re
import signal
import sys
from pathlib import Path

import aiohttp
import pytest

ROOT = Path(__file__).resolve().parents[1]
pytestmark = [pytest.mark.slow]


async def _line(stdout: asyncio.StreamReader, lines: list[str]) -> str:
    line = (await stdout.readline()).decode()
    if not line:
        raise AssertionError("the demo exited early:\n" + "".join(lines))
    lines.append(line)
    return line


async def test_demo_hmi_prints_a_login_that_works_and_ctrl_c_stops_it(tmp_path):
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "demos.hmi", "--port", "0", "--out", str(tmp_path), cwd=ROOT,
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.STDOUT)
    lines: list[str] = []
    try:
        assert proc.stdout is not None
        while not (await _line(proc.stdout, lines)).startswith("Ctrl-C"):
            pass
        text = "".join(lines)
        url = re.search(r"^HMI:\s+(http://127\.0\.0\.1:\d+/)$", text, re.M)
        login = re.search(r"^login:\s+user (\S+)\s+password (\S+)\s", text, re.M)
        assert url and login, text
        user, password = login.groups()
        assert user == "demo" and len(password) >= 12
        async with aiohttp.ClientSession(cookie_jar=aiohttp.CookieJar(unsafe=True)) as http:
            r = await http.post(url[1] + "login", data={"user": user, "password": password},
                                allow_redirects=False)
            assert r.status == 303, await r.text()
            me = await (await http.get(url[1] + "api/me")).json()
            assert me["name"] == "demo" and me["role"] == "engineer"
            st = await (await http.get(url[1] + "api/status")).json()
            assert st["demo-hmc"]["state"] == "IDLE" and st["demo-hmc"]["link_ok"]
        daemon_pid = int((tmp_path / "daemon.pid").read_text())
        proc.send_signal(signal.SIGINT)
        rest = (await proc.stdout.read()).decode()
        assert await proc.wait() == 0, text + rest
        assert "stopped: daemon and simulated CNC" in rest, rest
        assert "Traceback" not in text + rest
        with pytest.raises(ProcessLookupError):  # the daemon stopped (and was reaped)
            os.kill(daemon_pid, 0)
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
