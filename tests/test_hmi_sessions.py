"""HMI sessions across daemon restarts (real service, real HTTP, real journal file): a signed
cookie survives a restart, a new token, expiry, tampering and logout end it; the signing secret
is a private file in the state directory."""

from __future__ import annotations

import stat
import time
from pathlib import Path

import aiohttp
import pytest

from benchmarks.rigs.daemon_helpers import thesis_rows, thesis_setup, write_daemon_yaml
from daemon.analysis.replay_link import ReplayLink, prepare_from_rows
from daemon.config import load_daemon_config
from daemon.hmi.app import AUTH_KEY, COOKIE
from daemon.hmi.auth import SECRET_FILE, SESSION_TTL_S, Auth
from daemon.service.service import Service, ServiceError

TOKEN = "t0k3n-for-tests-0123456789"


class Daemon:
    """Starts and stops the service from one daemon.yaml, like systemd restarting it."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.svc: Service | None = None

    async def start(self) -> Service:
        setup = thesis_setup()
        rows = thesis_rows(setup)
        self.svc = Service(load_daemon_config(self.path),
                           lambda s: ReplayLink(rows, s.machine, delay_s=0.01),
                           prepare=prepare_from_rows(rows))
        await self.svc.start()
        return self.svc

    async def restart(self) -> Service:
        await self.stop()
        return await self.start()

    async def stop(self) -> None:
        if self.svc is not None:
            await self.svc.stop()
            self.svc = None

    @property
    def url(self) -> str:
        assert self.svc is not None and self.svc.hmi_url
        return self.svc.hmi_url

    @property
    def auth(self) -> Auth:
        assert self.svc is not None and self.svc._runner is not None
        return self.svc._runner.app[AUTH_KEY]  # type: ignore[return-value]


@pytest.fixture
async def daemon(tmp_path):
    d = Daemon(write_daemon_yaml(tmp_path, token=TOKEN))
    await d.start()
    yield d
    await d.stop()


async def sign_in(d: Daemon) -> tuple[str, str]:
    """(cookie value, CSRF token of the page) after the login form."""
    async with aiohttp.ClientSession(cookie_jar=aiohttp.CookieJar(unsafe=True)) as http:
        r = await http.post(d.url + "login", data={"token": TOKEN}, allow_redirects=False)
        assert r.status == 303
        cookie = r.cookies[COOKIE].value
        page = await (await http.get(d.url)).text()
    return cookie, page.split('name="csrf-token" content="')[1].split('"')[0]


async def status_code(d: Daemon, cookie: str) -> int:
    async with aiohttp.ClientSession() as http:
        r = await http.get(d.url + "api/status", headers={"Cookie": f"{COOKIE}={cookie}"})
        return r.status


async def post(d: Daemon, path: str, cookie: str, csrf: str) -> int:
    async with aiohttp.ClientSession() as http:
        r = await http.post(d.url + path, headers={"Cookie": f"{COOKIE}={cookie}",
                                                   "X-CSRF-Token": csrf})
        return r.status


async def test_session_survives_a_restart(daemon, tmp_path):
    cookie, csrf = await sign_in(daemon)
    assert await status_code(daemon, cookie) == 200
    secret = tmp_path / SECRET_FILE  # next to the journal: the state directory
    assert stat.S_IMODE(secret.stat().st_mode) == 0o600
    first = secret.read_bytes()
    await daemon.restart()
    assert secret.read_bytes() == first  # kept, not regenerated
    assert await status_code(daemon, cookie) == 200
    # The page loaded before the restart keeps working: its CSRF token is still accepted
    # (409 = nothing to abort, past the CSRF check; a wrong token is 403).
    assert await post(daemon, "api/machines/mill1/abort", cookie, csrf) == 409
    assert await post(daemon, "api/machines/mill1/abort", cookie, "x" * 32) == 403


async def test_a_new_token_signs_everybody_out(daemon):
    cookie, _ = await sign_in(daemon)
    daemon.path.write_text(daemon.path.read_text().replace(TOKEN, "an-0ther-token-9876543210"))
    await daemon.restart()
    assert await status_code(daemon, cookie) == 401


async def test_expired_tampered_and_foreign_cookies_are_refused(daemon):
    auth = daemon.auth
    good, _ = auth.new_session()
    assert await status_code(daemon, good) == 200
    expired, _ = auth.new_session(now=time.time() - SESSION_TTL_S - 1)
    assert await status_code(daemon, expired) == 401
    sid, exp, user, gen, sig = good.split(".")  # a token session: no user, no generation
    tampered = [f"{sid}.{int(exp) + 86400}.{user}.{gen}.{sig}",                 # longer life
                f"{sid[:-1]}{'A' if sid[-1] != 'A' else 'B'}.{exp}.{user}.{gen}.{sig}",  # id
                f"{sid}.{exp}.{user}.{gen}.{sig[:-1]}{'A' if sig[-1] != 'A' else 'B'}",  # sig
                f"{sid}.{exp}.admin.{gen}.{sig}",                       # a name slipped in
                f"{sid}.{exp}.{sig}", f"{sid}.{exp}", "", "a.b.c.d", "a.b.c.d.e"]
    for bad in tampered:
        assert await status_code(daemon, bad) == 401, bad
    foreign, _ = Auth(TOKEN).new_session()  # same token, another daemon's secret
    assert await status_code(daemon, foreign) == 401


async def test_logout_revokes_also_across_a_restart(daemon):
    cookie, csrf = await sign_in(daemon)
    other, _ = await sign_in(daemon)
    assert await post(daemon, "logout", cookie, csrf) == 200
    assert await status_code(daemon, cookie) == 401
    assert await status_code(daemon, other) == 200  # only that session ended
    await daemon.restart()
    assert await status_code(daemon, cookie) == 401
    assert await status_code(daemon, other) == 200


async def test_session_secret_must_be_private(tmp_path):
    d = Daemon(write_daemon_yaml(tmp_path, token=TOKEN))
    secret = tmp_path / SECRET_FILE
    secret.write_text("00" * 32)
    secret.chmod(0o644)
    with pytest.raises(ServiceError, match=r"hmi-session\.key: HMI session secret is readable "
                                           r"by others \(mode 0644\); chmod 600 it"):
        await d.start()
    secret.chmod(0o600)
    secret.write_text("not hex")
    with pytest.raises(ServiceError, match=r"hmi-session\.key: not a rumba HMI session secret"):
        await d.start()
