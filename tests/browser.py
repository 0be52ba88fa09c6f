"""Headless Chromium for the HMI tests, driven over the DevTools protocol with aiohttp (no
browser-automation dependency): start it on a free port, open a page, sign in, evaluate, wait."""

from __future__ import annotations

import asyncio
import base64
import contextlib
import os
import shutil
import tempfile
from collections.abc import AsyncIterator
from pathlib import Path

import aiohttp
import pytest


class CdpError(RuntimeError):
    """A DevTools protocol call answered with an error."""


class Cdp:
    """A tiny Chrome DevTools Protocol client over aiohttp websockets."""

    def __init__(self, ws: aiohttp.ClientWebSocketResponse) -> None:
        self.ws, self.n = ws, 0

    async def call(self, method: str, session: str | None = None, **params) -> dict:
        self.n += 1
        msg = {"id": self.n, "method": method, "params": params}
        if session:
            msg["sessionId"] = session
        await self.ws.send_json(msg)
        while True:
            reply = await self.ws.receive_json()
            if reply.get("id") == self.n:
                if "error" in reply:
                    raise CdpError(f"{method}: {reply['error']}")
                return reply["result"]

    async def eval(self, session: str, expr: str):
        r = await self.call("Runtime.evaluate", session, expression=expr, awaitPromise=True,
                            returnByValue=True)
        if "exceptionDetails" in r:
            raise CdpError(f"{expr[:80]}…: {r['exceptionDetails'].get('exception', r)}")
        return r["result"].get("value")

    async def wait_for(self, session: str, expr: str, timeout_s: float = 60.0):
        """Poll ``expr`` until truthy; an exception in the page (an element not there yet, a
        page between two documents) counts as not yet, and is named if time runs out."""
        last = None
        try:
            async with asyncio.timeout(timeout_s):
                while True:
                    try:
                        v = await self.eval(session, expr)
                    except CdpError as exc:
                        last, v = exc, None
                    if v:
                        return v
                    await asyncio.sleep(0.05)
        except TimeoutError:
            raise AssertionError(f"not true within {timeout_s:g} s: {expr} (last error: "
                                 f"{last})") from None

    async def page(self) -> str:
        """A new tab, attached: its session id."""
        target = (await self.call("Target.createTarget", url="about:blank"))["targetId"]
        sid = (await self.call("Target.attachToTarget", targetId=target, flatten=True))[
            "sessionId"]
        await self.call("Page.enable", sid)
        return sid

    async def _submit_login(self, sid: str, url: str, fill_js: str) -> None:
        """Open ``url``, wait for the login page it sends to, fill the form, submit it."""
        await self.call("Page.navigate", sid, url=url)
        await self.wait_for(sid, "location.pathname === '/login' && "
                                 "document.readyState === 'complete'")
        await self.eval(sid, fill_js + "document.querySelector('form').submit(); true")

    async def _hmi_live(self, sid: str) -> None:
        await self.wait_for(sid, "!!document.querySelector('.machine .start')")
        await self.wait_for(sid, "document.getElementById('conn').textContent === 'live'")

    async def sign_in(self, sid: str, url: str, token: str) -> None:
        """Open the HMI at ``url``, sign in with ``token``, wait for the live page."""
        await self._submit_login(sid, url, f"document.getElementById('token').value = '{token}';")
        await self._hmi_live(sid)

    async def sign_in_fleet(self, sid: str, url: str, token: str) -> None:
        """Open the fleet page at ``url``, sign in with ``token``, wait for the fleet table (the
        sign-in lands on /, whatever page was asked)."""
        await self._submit_login(sid, url, f"document.getElementById('token').value = '{token}';")
        await self.wait_for(sid, "!!document.querySelector('table.fleet-table')")

    async def sign_in_user(self, sid: str, url: str, user: str, password: str,
                           live: bool = True) -> None:
        """Open the HMI at ``url`` and sign in with an account (``hmi.users_file``)."""
        await self._submit_login(sid, url, f"document.getElementById('user').value = {user!r};"
                                 f"document.getElementById('password').value = {password!r};")
        if live:
            await self._hmi_live(sid)

    async def screenshot(self, sid: str, path: Path, whole_page: bool = False) -> None:
        shot = await self.call("Page.captureScreenshot", sid, captureBeyondViewport=whole_page)
        path.write_bytes(base64.b64decode(shot["data"]))


@contextlib.asynccontextmanager
async def chromium(profile: Path, window: str = "1280,900") -> AsyncIterator[Cdp]:
    """Headless Chromium on a free DevTools port (skips when not installed: `make peers`)."""
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        pytest.skip("chromium not installed (make peers)")
    own_tmp = tempfile.mkdtemp(prefix="rumba-chromium-")
    proc = await asyncio.create_subprocess_exec(
        exe, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync",
        f"--user-data-dir={profile}", "--remote-debugging-port=0", f"--window-size={window}",
        "about:blank", stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.DEVNULL,
        # its singleton socket and cookie go to a org.chromium.Chromium.* folder in TMPDIR,
        # left behind when it is killed: a folder of its own, removed below (short: a socket
        # path is at most 107 bytes, a test's tmp_path under xdist is longer)
        env={**os.environ, "TMPDIR": own_tmp})
    try:
        port_file = profile / "DevToolsActivePort"
        async with asyncio.timeout(30):
            while not port_file.is_file() or len(port_file.read_text().split()) < 2:
                await asyncio.sleep(0.05)
        port, path = port_file.read_text().split()[:2]
        async with aiohttp.ClientSession() as http, \
                http.ws_connect(f"ws://127.0.0.1:{port}{path}", max_msg_size=0) as ws:
            cdp = Cdp(ws)
            yield cdp
            with contextlib.suppress(Exception):
                await cdp.call("Browser.close")
    finally:
        if proc.returncode is None:
            with contextlib.suppress(TimeoutError):  # closing: it removes what it made
                await asyncio.wait_for(proc.wait(), 5)
        if proc.returncode is None:
            proc.kill()
        await proc.wait()
        shutil.rmtree(own_tmp, ignore_errors=True)


async def tick_preflight(cdp: Cdp, sid: str, shot: Path | None = None) -> None:
    """The Start button's pre-flight dialog: open, its Start refused until every item is
    ticked, then ticked and confirmed (``shot``: a screenshot with every item ticked)."""
    dlg = "document.getElementById('preflight')"
    await cdp.wait_for(sid, f"{dlg}.open")
    assert await cdp.eval(sid, f"{dlg}.querySelector('.pf-start').disabled")
    await cdp.eval(sid, f"[...{dlg}.querySelectorAll('.pf-items input')].forEach(b => {{"
                        "b.checked = true; b.dispatchEvent(new Event('change')); }); true")
    assert not await cdp.eval(sid, f"{dlg}.querySelector('.pf-start').disabled")
    if shot is not None:
        await cdp.screenshot(sid, shot)
    await cdp.eval(sid, f"{dlg}.querySelector('.pf-start').click(); true")
