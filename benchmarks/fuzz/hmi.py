"""Target 5: the HMI routes over real HTTP (service with a replay link, free loopback port)."""

from __future__ import annotations

import asyncio
import logging
import random
import tempfile
import time
from pathlib import Path
from typing import Any

from benchmarks.fuzz.common import Tally, rand_text

TOKEN = "t0k3n-for-fuzzing-0123456789"
PUBLIC = ("/login", "/hmi.css")
METHODS = ("GET", "GET", "GET", "POST", "POST", "HEAD", "PUT", "DELETE", "OPTIONS", "PATCH")
AUTHS = ("none", "bad-bearer", "bearer", "cookie", "cookie+csrf", "cookie+csrf+bad-origin")


class _Errors(logging.Handler):
    """Collects records logged with exception information (an unhandled error)."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        if record.levelno >= logging.ERROR and record.exc_info and record.exc_info[0]:
            self.records.append(record)


def _path(rng: random.Random) -> str:
    q = rng.choice(("", "", "?limit=-1", "?limit=0", "?limit=99999999999999999999999",
                    "?limit=1e99", "?limit=nan", "?limit=%00", "?limit=١٢", "?machine=../../x",
                    "?machine=%0a%0d", "?trigger=cli", "?run=../../etc/passwd", "?limit=1&limit=2",
                    "?" + "a=1&" * 2000))
    p = rng.choice((
        "/", "/login", "/logout", "/hmi.js", "/hmi.css", "/api/status", "/api/runs", "/api/runs",
        "/api/events", "/api/machines/mill1/start", "/api/machines/mill1/abort",
        "/api/machines/%2e%2e/start", "/api/machines/" + "m" * 5000 + "/start",
        "/reports/../../etc/passwd.html", "/reports/%2e%2e%2f%2e%2e%2fx.json",
        "/reports/" + "r" * 64 + ".json", "/reports/nonexistent-run.html", "/reports/.json",
        "/api/machines/mill1%00/abort", "//api/status", "/api/status/", "/API/STATUS",
        "/" + rand_text(rng, 20).encode("utf-8", "surrogatepass").hex()))
    return p + q


async def _campaign(rng: random.Random, n: int, tally: Tally) -> None:
    import aiohttp
    from yarl import URL

    from benchmarks.rigs.daemon_helpers import thesis_rows, thesis_setup, write_daemon_yaml
    from daemon.analysis.replay_link import ReplayLink, prepare_from_rows
    from daemon.config import load_daemon_config
    from daemon.service.service import Service

    errors = _Errors()
    logging.getLogger().addHandler(errors)
    with tempfile.TemporaryDirectory(prefix="rumba-fuzz-") as tmp_s:
        cfg = load_daemon_config(write_daemon_yaml(Path(tmp_s), token=TOKEN))
        rows = thesis_rows(thesis_setup())
        svc = Service(cfg, lambda s: ReplayLink(rows, s.machine, delay_s=0.001),
                      prepare=prepare_from_rows(rows))
        await svc.start()
        base = svc.hmi_url.rstrip("/")
        timeout = aiohttp.ClientTimeout(total=5)
        jar = aiohttp.CookieJar(unsafe=True)
        try:
            async with aiohttp.ClientSession(cookie_jar=jar, timeout=timeout) as logged, \
                    aiohttp.ClientSession(timeout=timeout,
                                          cookie_jar=aiohttp.DummyCookieJar()) as anon:
                await logged.post(base + "/login", data={"token": TOKEN}, allow_redirects=False)
                page = await (await logged.get(base + "/")).text()
                csrf = (page.split('name="csrf-token" content="')[1].split('"')[0]
                        if 'name="csrf-token"' in page else "")
                for i in range(n):
                    await _one(rng, i, tally, errors, base, logged, anon, csrf, URL)
        finally:
            await svc.stop()
            logging.getLogger().removeHandler(errors)


async def _one(rng: random.Random, i: int, tally: Tally, errors: _Errors, base: str,
               logged: Any, anon: Any, csrf: str, url_cls: Any) -> None:
    import aiohttp

    method, path, auth = rng.choice(METHODS), _path(rng), rng.choice(AUTHS)
    headers: dict[str, str] = {}
    if auth == "bearer":
        headers["Authorization"] = f"Bearer {TOKEN}"
    elif auth == "bad-bearer":
        headers["Authorization"] = rng.choice((f"Bearer {TOKEN[:-1]}X", "Bearer ", "Basic eA==",
                                               f"bearer {TOKEN}", f"Bearer {TOKEN}\x00"[:60]))
    if auth.startswith("cookie+csrf"):
        headers["X-CSRF-Token"] = csrf
    if auth.endswith("bad-origin"):
        headers["Origin"] = rng.choice(("http://evil.example", "null", "http://127.0.0.1",
                                        "http://127.0.0.1:1", rand_text(rng, 10)))
    r = rng.random()
    if r < 0.1:
        headers["Host"] = rng.choice(("evil.example", "127.0.0.1:1", "", "x" * 300, "[::1]"))
    elif r < 0.15:
        headers["X-Big"] = "h" * rng.choice((100, 8000, 9000))
    headers = {k: v for k, v in headers.items()
               if all(0x20 <= ord(c) < 0x7F for c in v) and v}
    if auth.endswith("bad-origin") and "Origin" not in headers:
        auth = "cookie+csrf"  # the random Origin could not be sent: an ordinary request
    body: bytes | dict[str, str] | None = None
    if method in ("POST", "PUT", "PATCH") and rng.random() < 0.6:
        if path.startswith("/login") and rng.random() < 0.7:
            body = {"token": rng.choice(("wrong", "", TOKEN[:-1], rand_text(rng, 30))),
                    rand_text(rng, 5) or "x": rand_text(rng, 5)}
        else:
            body = bytes(rng.randrange(256) for _ in range(rng.choice((0, 10, 1000, 70_000))))
    session = logged if auth.startswith("cookie") else anon
    before = len(errors.records)
    desc = (f"case {i}: {method} {path[:120]!r} auth={auth} headers="
            f"{ {k: v[:40] for k, v in headers.items()} } body={type(body).__name__}"
            f"{len(body) if body is not None else ''}")
    t0 = time.perf_counter()
    status = 0
    try:
        async with session.request(method, url_cls(base + path, encoded=True), headers=headers,
                                   data=body, allow_redirects=False) as resp:
            status = resp.status
            if not resp.headers.get("Content-Type", "").startswith("text/event-stream"):
                await resp.read()
    except TimeoutError:
        tally.add("hang", f"{desc} -> no answer in 5 s")
        return
    except (aiohttp.ClientError, ValueError) as e:
        tally.add("clean", "", "")  # the client refused to send it or the server closed
        tally.note(f"client-side {type(e).__name__}")
        return
    await asyncio.sleep(0)
    logged_errs = errors.records[before:]
    bare = path.split("?")[0]
    unauth = auth in ("none", "bad-bearer")
    state_changing = method not in ("GET", "HEAD", "OPTIONS")
    if (logged_errs and 400 <= status < 500
            and all(rec.name == "aiohttp.server" for rec in logged_errs)):
        # aiohttp's own parser refusing a request (LineTooLong, …) logs it with a traceback.
        exc = logged_errs[0].exc_info[0].__name__  # type: ignore[index]
        kind = f"note: aiohttp.server logged a traceback for HTTP {status} ({exc})"
        tally.note(kind)
        tally.kinds.setdefault(kind, desc)
        tally.add("clean")
    elif (status >= 500 and status != 503) or logged_errs:
        what = (f"{logged_errs[0].name}: {logged_errs[0].getMessage()[:80]} "
                f"({logged_errs[0].exc_info[0].__name__})" if logged_errs  # type: ignore[index]
                else "")
        tally.add("traceback", f"{desc} -> HTTP {status} {what}", f"HTTP {status}")
    elif 200 <= status < 400 and status != 302 and unauth and bare not in PUBLIC:
        tally.add("wrong", f"{desc} -> HTTP {status} without credentials", f"unauth {status}")
    elif (200 <= status < 300 and state_changing and bare not in PUBLIC
          and auth in ("cookie", "cookie+csrf+bad-origin")):
        tally.add("wrong", f"{desc} -> HTTP {status} (cookie without CSRF / cross-origin)",
                  f"csrf {status}")
    elif bare == "/login" and method == "POST" and status == 303:
        tally.add("wrong", f"{desc} -> login accepted a wrong token", "login")
    else:
        tally.add("accepted" if status < 400 else "clean")
    if time.perf_counter() - t0 > 5:
        tally.note("slow answer (> 5 s)")


def fuzz(rng: random.Random, n: int) -> Tally:
    tally = Tally("HMI routes")
    asyncio.run(_campaign(rng, n, tally))
    return tally
