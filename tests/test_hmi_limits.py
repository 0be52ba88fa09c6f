"""HMI limits over real HTTP on a free loopback port: the daemon-wide wrong-token limiter (also
against parallel requests), header and body read timeouts, size caps, Host / Origin checks
(DNS rebinding), bounded query values and run ids.

Nothing here races the machine's speed: the limiter runs on an injected clock that only the test
moves (a loaded machine took 1.8 s for 200 requests, longer than a real 1 s lockout), and the
0.4 s header timeout, which aiohttp measures on the loop's own clock from the moment it accepts
a connection, is only served to the tests of that timeout (a loop stalled that long would cut
any other test's request before its headers were read)."""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass

import aiohttp
import pytest
from aiohttp import web

from daemon.hmi.app import AUTH_KEY, COOKIE, LIMITER_KEY, STORE_KEY, create_app
from daemon.hmi.limits import AuthLimiter, HmiLimits, Origins, client_key
from daemon.store.journal import Store

TOKEN = "t0k3n-for-tests-0123456789"
FAST = HmiLimits(header_timeout_s=0.4, body_timeout_s=0.4, linger_s=0.2)
"""Short header and body timeouts: for the tests of those timeouts."""
LIMITS = HmiLimits(body_timeout_s=0.4, linger_s=0.2)
"""Everything else: the body timeout is short (a cut body is only ever too slow, never cut
early by a stalled loop, since it starts once the headers are in), the header timeout is the
daemon's."""


class Clock:
    """The limiter's clock (``AuthLimiter(…, clock)``): stands still until the test moves it."""

    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


@dataclass
class Hmi:
    app: web.Application
    port: int
    clock: Clock

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}/"


async def serve(tmp_path, limits: HmiLimits = LIMITS, **kw) -> tuple[web.AppRunner, Hmi]:
    """The HMI app served like ``Service._start_hmi`` does (AppRunner, no runner options), its
    wrong-token limiter on a ``Clock`` the test moves."""
    store = Store(tmp_path / "journal.sqlite")
    app = create_app({}, store, TOKEN, limits=limits, **kw)
    clock = Clock()
    app[LIMITER_KEY] = AuthLimiter(limits, clock)  # before setup: the app is frozen then
    runner = web.AppRunner(app, access_log=None, handle_signals=False)
    await runner.setup()
    site = web.TCPSite(runner, "127.0.0.1", 0)
    await site.start()
    port = site._server.sockets[0].getsockname()[1]  # type: ignore[union-attr]
    return runner, Hmi(app, port, clock)


@pytest.fixture
async def hmi(tmp_path) -> AsyncIterator[Hmi]:
    runner, h = await serve(tmp_path)
    yield h
    await runner.cleanup()


@pytest.fixture
async def fast_hmi(tmp_path) -> AsyncIterator[Hmi]:
    """Served with ``FAST``: a 0.4 s header timeout."""
    runner, h = await serve(tmp_path, FAST)
    yield h
    await runner.cleanup()


def bearer(token: str = TOKEN) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


# ------------------------------------------------------------------------- wrong tokens


async def test_parallel_wrong_tokens_are_locked_out_before_the_token_is_checked(hmi, caplog):
    auth = hmi.app[AUTH_KEY]
    checked = []
    real = auth.token_ok
    auth.token_ok = lambda t: checked.append(t) or real(t)  # type: ignore[method-assign]
    cookie, _ = auth.new_session()
    async with aiohttp.ClientSession() as http:
        async def guess(i: int) -> int:
            async with http.get(hmi.url + "api/status", headers=bearer(f"guess-{i:020d}")) as r:
                return r.status
        t0 = time.perf_counter()
        codes = await asyncio.gather(*(guess(i) for i in range(200)))
        elapsed = time.perf_counter() - t0
        assert codes.count(401) == LIMITS.free_failures
        assert codes.count(429) == 200 - LIMITS.free_failures
        assert len(checked) == LIMITS.free_failures  # the other 195 never reached the token
        print(f"\n200 parallel guesses in {elapsed:.2f} s: {len(checked)} tokens checked")
        # Locked out however long that took (the limiter's clock has not moved) and whatever
        # the test does next: even the right token is not looked at now …
        r = await http.get(hmi.url + "api/status", headers=bearer())
        assert r.status == 429 and r.headers["Retry-After"] == "1"  # lockout_base_s
        r = await http.post(hmi.url + "login", data={"token": TOKEN}, allow_redirects=False)
        assert r.status == 429
        assert len(checked) == LIMITS.free_failures
        # … but a signed-in operator keeps working (a cookie is not a token guess).
        r = await http.get(hmi.url + "api/status", headers={"Cookie": f"{COOKIE}={cookie}"})
        assert r.status == 200
        hmi.clock.t += LIMITS.lockout_base_s / 2
        assert (await http.get(hmi.url + "api/status", headers=bearer())).status == 429
        hmi.clock.t += LIMITS.lockout_base_s / 2  # over: the right token is checked, accepted
        assert (await http.get(hmi.url + "api/status", headers=bearer())).status == 200
        assert len(checked) == LIMITS.free_failures + 1
    assert any("wrong token (bearer) from loopback" in m and "locked out" in m
               for m in caplog.messages)


async def test_wrong_login_forms_count_too_and_success_resets(hmi):
    limiter = hmi.app[LIMITER_KEY]
    async with aiohttp.ClientSession() as http:
        for _ in range(LIMITS.free_failures - 1):
            r = await http.post(hmi.url + "login", data={"token": "wrong"})
            assert r.status == 401
        r = await http.post(hmi.url + "login", data={"token": TOKEN}, allow_redirects=False)
        assert r.status == 303
        assert limiter.retry_after("127.0.0.1") == 0  # the right token restarted the count
        for _ in range(LIMITS.free_failures):
            assert (await http.post(hmi.url + "login", data={"token": "x"})).status == 401
        r = await http.post(hmi.url + "login", data={"token": "x"})
        assert r.status == 429  # locked out for lockout_base_s of the limiter's clock
        hmi.clock.t += LIMITS.lockout_base_s
        r = await http.post(hmi.url + "login", data={"token": "x"})
        assert r.status == 401  # tried again after the lockout: wrong, and locked out longer
        assert limiter.retry_after("127.0.0.1") == 2 * LIMITS.lockout_base_s


def test_lockout_doubles_and_is_capped():
    clock = Clock()
    lim = AuthLimiter(HmiLimits(free_failures=2, lockout_base_s=1, lockout_max_s=8), clock)
    waits = []
    for _ in range(8):
        assert lim.retry_after("10.0.0.1") == 0
        lim.failed("10.0.0.1", "bearer")
        waits.append(lim.retry_after("10.0.0.1"))
        clock.t += waits[-1]
    assert waits == [0, 1, 2, 4, 8, 8, 8, 8]
    assert lim.retry_after("10.0.0.2") == 0  # another client is not locked out


def test_many_addresses_share_one_budget_but_loopback_keeps_its_own():
    clock = Clock()
    limits = HmiLimits(global_burst=20, global_refill_s=30)
    lim = AuthLimiter(limits, clock)
    tried = 0
    for i in range(1000):  # an address sweep: each address would have 5 free tries
        addr = f"10.{i // 250}.{i % 250}.7"
        if lim.retry_after(addr) == 0:
            tried += 1
            lim.failed(addr, "bearer")
    assert tried == limits.global_burst
    assert lim.retry_after("192.168.1.9") == pytest.approx(30)
    assert lim.retry_after("127.0.0.1") == 0  # the machine's own operator is not locked out
    clock.t += 60  # refilled: two more tries in a minute
    assert sum(lim.retry_after(f"172.16.0.{i}") == 0 and not lim.failed(f"172.16.0.{i}", "x")
               for i in range(10)) == 2


def test_client_keys_group_ipv6_and_loopback():
    assert client_key("127.0.0.1") == client_key("127.8.9.10") == client_key("::1") == "loopback"
    assert client_key("2001:db8::1") == client_key("2001:db8::ffff:1") == "2001:db8::/64"
    assert client_key("::ffff:10.1.2.3") == "10.1.2.3"
    assert client_key(None) == client_key("garbage") == "local"


def test_remembered_clients_are_bounded():
    clock = Clock()
    lim = AuthLimiter(HmiLimits(max_clients=50, global_burst=10**6), clock)
    for i in range(500):
        lim.failed(f"10.0.{i // 250}.{i % 250}", "bearer")
        clock.t += 0.01
    assert len(lim._clients) <= 51


# ---------------------------------------------------------------------- slow and big requests


async def _until_closed(reader: asyncio.StreamReader, within_s: float = 5.0) -> bytes:
    """Everything the server sends until it closes the connection (fails after within_s)."""
    async with asyncio.timeout(within_s):
        return await reader.read()


async def test_partial_header_is_disconnected(fast_hmi):
    # The server's timer starts when it accepts the connection, so the time is taken before
    # connecting: taken after, a loop stalled in between made the wait look short.
    t0 = time.monotonic()
    reader, writer = await asyncio.open_connection("127.0.0.1", fast_hmi.port)
    writer.write(b"GET /api/status HTTP/1.1\r\nHost: 127.0.0.1\r\n")  # no blank line: never ends
    assert await _until_closed(reader) == b""
    assert time.monotonic() - t0 >= FAST.header_timeout_s * 0.9
    writer.close()


async def test_header_sent_byte_by_byte_is_disconnected(fast_hmi):
    reader, writer = await asyncio.open_connection("127.0.0.1", fast_hmi.port)

    async def dribble() -> None:  # slowloris: a byte now and then, never the end of the head
        for b in b"GET /api/status HTTP/1.1\r\nX-Slow: " + b"a" * 10_000:
            writer.write(bytes([b]))
            await asyncio.sleep(0.02)

    t = asyncio.create_task(dribble())
    try:
        assert await _until_closed(reader) == b""
    except ConnectionResetError:
        # Also closed: a byte sent after the server closed, before this loop had read the
        # close (a loaded machine), is answered with a reset, which then replaces the EOF.
        pass
    finally:
        t.cancel()
        writer.close()


async def test_slow_body_is_cut(hmi):
    reader, writer = await asyncio.open_connection("127.0.0.1", hmi.port)
    writer.write(b"POST /login HTTP/1.1\r\nHost: 127.0.0.1:%d\r\nContent-Type: "
                 b"application/x-www-form-urlencoded\r\nContent-Length: 100\r\n\r\ntoken=abc"
                 % hmi.port)
    answer = await _until_closed(reader)
    assert answer.startswith(b"HTTP/1.1 408 "), answer[:80]
    writer.close()


async def test_slow_body_of_an_api_call_is_cut(hmi):
    reader, writer = await asyncio.open_connection("127.0.0.1", hmi.port)
    writer.write(b"POST /api/machines/m/start HTTP/1.1\r\nHost: 127.0.0.1:%d\r\nAuthorization:"
                 b" Bearer %s\r\nContent-Length: 100\r\n\r\n{" % (hmi.port, TOKEN.encode()))
    answer = await _until_closed(reader)
    assert answer.startswith(b"HTTP/1.1 408 "), answer[:80]
    writer.close()


async def test_sizes_are_capped(hmi):
    async with aiohttp.ClientSession() as http:
        r = await http.post(hmi.url + "login", data={"token": "x" * (LIMITS.max_body_bytes + 1)})
        assert r.status == 413
        r = await http.get(hmi.url + "api/runs?machine=" + "m" * LIMITS.max_line_bytes)
        assert r.status in (400, 414)
        many = {f"X-H{i}": "v" for i in range(LIMITS.max_headers + 1)}
        r = await http.get(hmi.url + "api/status", headers={**bearer(), **many})
        assert r.status == 400


# ------------------------------------------------------------------------- Host and Origin


async def _status(hmi: Hmi, path: str, method: str = "GET", **headers: str) -> int:
    async with aiohttp.ClientSession() as http, \
            http.request(method, hmi.url + path, headers=headers, allow_redirects=False) as r:
        return r.status


async def test_host_must_be_an_allowed_name(hmi):
    auth = bearer()["Authorization"]
    p = hmi.port
    for host in (f"127.0.0.1:{p}", f"localhost:{p}", f"LOCALHOST:{p}", f"[::1]:{p}",
                 f"0.0.0.0:{p}"):
        assert await _status(hmi, "api/status", Authorization=auth, Host=host) == 200, host
    # DNS rebinding: evil.example now resolves to 127.0.0.1; the browser still says its name.
    for host in (f"evil.example:{p}", "evil.example", f"127.0.0.1:{p + 1}", f"x@127.0.0.1:{p}",
                 f"127.0.0.1:{p}/x", ""):
        assert await _status(hmi, "api/status", Authorization=auth, Host=host) == 421, host
    assert await _status(hmi, "login", Host=f"evil.example:{p}") == 421  # public pages too


async def test_missing_host_is_refused(hmi):
    reader, writer = await asyncio.open_connection("127.0.0.1", hmi.port)
    writer.write(b"GET /login HTTP/1.0\r\n\r\n")
    assert (await _until_closed(reader)).startswith(b"HTTP/1.0 421 ")
    writer.close()


async def test_origin_is_compared_with_the_allowed_origins_not_the_host(hmi):
    cookie, csrf = hmi.app[AUTH_KEY].new_session()
    p = hmi.port
    h = {"Cookie": f"{COOKIE}={cookie}", "X-CSRF-Token": csrf}
    path = "api/machines/none/abort"  # 404 = past the Origin and CSRF checks
    assert await _status(hmi, path, "POST", **h) == 404
    assert await _status(hmi, path, "POST", Origin=f"http://localhost:{p}", **h) == 404
    assert await _status(hmi, path, "POST", Origin=f"http://127.0.0.1:{p}", **h) == 404
    for origin in (f"http://evil.example:{p}", f"https://127.0.0.1:{p}", "null",
                   f"http://127.0.0.1:{p + 1}", f"http://127.0.0.1:{p}.evil.example"):
        assert await _status(hmi, path, "POST", Origin=origin, **h) == 403, origin
    # Fetch metadata, set by the browser: a privacy "null" from the page itself passes, any
    # cross-site request is refused whatever its Origin says.
    same, cross = {"Sec-Fetch-Site": "same-origin"}, {"Sec-Fetch-Site": "cross-site"}
    assert await _status(hmi, path, "POST", Origin="null", **same, **h) == 404
    assert await _status(hmi, path, "POST", Origin=f"http://127.0.0.1:{p}", **cross, **h) == 403
    assert await _status(hmi, path, "POST", **cross, **h) == 403
    # The rebinding page: its Origin equals its Host, which the old check accepted.
    evil = f"evil.example:{p}"
    assert await _status(hmi, path, "POST", Origin=f"http://{evil}", Host=evil, **h) == 421
    r = await _status(hmi, "login", "POST", Origin="http://evil.example")
    assert r == 403  # login CSRF


async def test_configured_public_origin(tmp_path):
    runner, hmi = await serve(tmp_path, public_origins=["http://rumba.plant.example:8470/"],
                              bind_host="127.0.0.1")
    try:
        cookie, csrf = hmi.app[AUTH_KEY].new_session()
        h = {"Cookie": f"{COOKIE}={cookie}", "X-CSRF-Token": csrf}
        assert await _status(hmi, "api/status", Host="rumba.plant.example:8470", **h) == 200
        assert await _status(hmi, "api/machines/x/abort", "POST", Host="rumba.plant.example:8470",
                             Origin="http://rumba.plant.example:8470", **h) == 404
        assert await _status(hmi, "api/status", Host="rumba.plant.example:8471", **h) == 421
    finally:
        await runner.cleanup()
    with pytest.raises(ValueError, match="not scheme://host"):
        create_app({}, Store(tmp_path / "j2.sqlite"), TOKEN, public_origins=["rumba.plant"])


# ------------------------------------------------------------------------- query values, ids


async def test_numeric_query_values_are_bounded(hmi):
    auth = bearer()["Authorization"]
    for bad in ("-1", "0", "501", "1e3", "+5", " 5", "", "5.0", "99999999999999999999", "٣"):
        async with aiohttp.ClientSession() as http, http.get(
                hmi.url + "api/runs", params={"limit": bad}, headers=bearer()) as r:
            assert r.status == 400, bad
            assert "limit must be an integer from 1 to 500" in await r.text()
    for good in ("1", "500"):
        assert await _status(hmi, f"api/runs?limit={good}", Authorization=auth) == 200
    assert await _status(hmi, "api/runs?machine=" + "m" * 65, Authorization=auth) == 400


async def test_bad_run_ids_never_reach_the_store(hmi):
    store = hmi.app[STORE_KEY]
    asked: list[str] = []
    real = store.report
    store.report = lambda run_id: asked.append(run_id) or real(run_id)  # type: ignore
    auth = bearer()["Authorization"]
    for bad in ("a.b", "_x", "-x", "..", "a_b", "x" * 65):
        assert await _status(hmi, f"reports/{bad}.html", Authorization=auth) == 404, bad
    assert asked == []
    assert await _status(hmi, "reports/20200101T000000Z-0a0a.json", Authorization=auth) == 404
    assert asked == ["20200101T000000Z-0a0a"]


async def test_compressed_and_broken_bodies_are_refused_quietly(hmi, caplog):
    for encoding, body in (("gzip", b"\x00\x00"), ("deflate", b"0123456789"), ("br", b"x")):
        for path, auth in (("login", {}), ("api/machines/m/start", bearer())):
            async with aiohttp.ClientSession() as http, http.post(
                    hmi.url + path, data=body, headers={
                        "Content-Encoding": encoding, **auth,
                        "Content-Type": "application/x-www-form-urlencoded"}) as r:
                assert r.status == 415, (encoding, path)
    reader, writer = await asyncio.open_connection("127.0.0.1", hmi.port)
    writer.write(b"POST /login HTTP/1.1\r\nHost: 127.0.0.1:%d\r\nTransfer-Encoding: chunked\r\n"
                 b"Content-Type: application/x-www-form-urlencoded\r\n\r\nzz\r\n" % hmi.port)
    answer = await _until_closed(reader)
    assert answer == b"" or answer.startswith((b"HTTP/1.0 400 ", b"HTTP/1.1 400 ")), answer[:80]
    writer.close()
    assert not [r for r in caplog.records if r.exc_info or r.levelno >= 40]


def test_allowed_hosts():
    o = Origins("rumba.local", ["https://hmi.plant.example"])
    lan = ("192.168.1.5", 8470)
    assert o.host_ok("rumba.local:8470", lan, "http")
    assert o.host_ok("192.168.1.5:8470", lan, "http")
    assert not o.host_ok("localhost:8470", lan, "http")  # not a loopback connection
    assert o.host_ok("hmi.plant.example", lan, "https")  # default port of the origin
    assert not o.host_ok("hmi.plant.example", lan, "http")
    assert o.origin_ok("https://hmi.plant.example:443", lan, "https")
    assert o.host_ok("127.0.0.1:8470", ("::ffff:127.0.0.1", 8470), "http")  # dual stack
    for bad in ("", "rumba.local:8470:1", "rumba.local:x", "rumba.local:8470 ", "a b",
                "rumba.local\r\n", "[::1", "rumba.local@evil"):
        assert not o.host_ok(bad, lan, "http"), bad
