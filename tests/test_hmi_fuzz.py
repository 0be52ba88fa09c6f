"""Property-based fuzzing of the HMI over raw sockets (the real service on a free loopback port,
run in its own thread): random methods, paths, query strings, headers, credentials and bodies
never give a 500, never log a traceback or an error, and never succeed without credentials."""

from __future__ import annotations

import asyncio
import logging
import socket
import threading
from collections.abc import Iterator
from dataclasses import dataclass

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from benchmarks.rigs.daemon_helpers import thesis_rows, thesis_setup, write_daemon_yaml
from daemon.analysis.replay_link import ReplayLink, prepare_from_rows
from daemon.config import load_daemon_config
from daemon.hmi.app import AUTH_KEY, COOKIE, LIMITER_KEY, PUBLIC
from daemon.hmi.limits import HmiLimits
from daemon.service.service import Service

TOKEN = "t0k3n-for-tests-0123456789"


class Records(logging.Handler):
    """Every log record of every thread at WARNING and above."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


@dataclass
class Target:
    port: int
    cookie: str
    csrf: str
    records: Records


@pytest.fixture(scope="module")
def target(tmp_path_factory) -> Iterator[Target]:
    tmp = tmp_path_factory.mktemp("hmi-fuzz")
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    rows = thesis_rows(thesis_setup())
    svc = Service(load_daemon_config(write_daemon_yaml(tmp, token=TOKEN)),
                  lambda s: ReplayLink(rows, s.machine, delay_s=0.01),
                  prepare=prepare_from_rows(rows))
    asyncio.run_coroutine_threadsafe(svc.start(), loop).result(60)
    app = svc._runner.app  # type: ignore[union-attr]
    # Wrong tokens are part of the fuzz: keep the limiter from turning everything into 429s
    # (it is tested on its own in test_hmi_limits).
    app[LIMITER_KEY].limits = HmiLimits(free_failures=10**9, global_burst=10**9)
    cookie, csrf = app[AUTH_KEY].new_session()
    records = Records()
    logging.getLogger().addHandler(records)
    try:
        yield Target(int(svc.hmi_url.rsplit(":", 1)[1].strip("/")), cookie, csrf, records)
    finally:
        logging.getLogger().removeHandler(records)
        asyncio.run_coroutine_threadsafe(svc.stop(), loop).result(60)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(10)
        loop.close()


ROUTES = ["/", "/login", "/logout", "/hmi.js", "/hmi.css", "/api/status", "/api/runs",
          "/api/events", "/api/machines/mill1/start", "/api/machines/mill1/abort",
          "/api/machines/nope/start", "/reports/20200101T000000Z-0a0a.html",
          "/reports/x.json", "/reports/", "/api/", "/favicon.ico", "/compensation.js",
          "/api/compensation?machine=mill1", "/api/compensation/confirm",
          "/api/compensation/rollback", "/api/maps", "/maps.js",
          "/maps/map-20200101-000000-0a0a/map.html", "/maps/x/map.json"]
# Bytes a request line may carry (no space, CR, LF), plus percent escapes and dot segments.
URL_CHARS = st.characters(min_codepoint=0x21, max_codepoint=0x7E)
SEGMENT = st.one_of(st.text(URL_CHARS, max_size=12), st.sampled_from(
    ["..", ".", "%2e%2e", "%2F", "%00", "%ff", "mill1", "20200101T000000Z-0a0a.html",
     "a.b.html", "\u00e9"]))
PATH = st.one_of(st.sampled_from(ROUTES),
                 st.lists(SEGMENT, min_size=1, max_size=5).map(lambda p: "/" + "/".join(p)),
                 st.tuples(st.sampled_from(ROUTES), SEGMENT).map("/".join))
QUERY_VALUE = st.one_of(st.sampled_from(["-1", "0", "1", "500", "501", "1e3", "", "%00",
                                         "9" * 30, "cli", "mill1", "%ff%fe"]),
                        st.text(URL_CHARS.filter(lambda c: c not in "&#"), max_size=10))
QUERY = st.lists(st.tuples(st.sampled_from(["limit", "machine", "trigger", "x", "limit[]"]),
                           QUERY_VALUE), max_size=4).map(
    lambda kv: "?" + "&".join(f"{k}={v}" for k, v in kv) if kv else "")
METHOD = st.one_of(st.sampled_from(["GET", "POST"]),
                   st.sampled_from(["GET", "POST", "HEAD", "PUT", "DELETE", "OPTIONS", "PATCH"]),
                   st.text(st.sampled_from("ABCDEFGHIJKLMNOPQRSTUVWXYZ"), min_size=1, max_size=8))
CREDENTIAL = st.sampled_from(["none", "bearer", "bearer-wrong", "cookie", "cookie-wrong",
                              "basic", "bearer-empty"])
HEADER_VALUE = st.text(st.characters(min_codepoint=0x20, max_codepoint=0x7E), max_size=40)
EXTRA = st.lists(st.tuples(st.sampled_from(
    ["Origin", "X-CSRF-Token", "Content-Type", "Cookie", "Accept", "X-Forwarded-For",
     "Forwarded", "Content-Encoding", "Expect", "Sec-Fetch-Site", "X-Fuzz"]),
    st.one_of(HEADER_VALUE, st.sampled_from(
        ["gzip", "deflate", "br", "zstd", "identity", "null", "same-origin", "cross-site",
         "100-continue", "http://127.0.0.1", "http://evil.example"]))), max_size=4)
CONTENT_TYPE = st.sampled_from([None, "application/x-www-form-urlencoded", "application/json",
                                "multipart/form-data; boundary=x", "text/plain; charset=bogus",
                                "application/x-www-form-urlencoded; charset=utf-16"])
ENCODING = st.sampled_from([None, None, "gzip", "deflate", "br", "identity", "zstd", "x"])
BODY = st.one_of(st.binary(max_size=300), st.sampled_from(
    [b"", b"token=" + TOKEN.encode(), b"token=wrong", b"token=%ff%fe", b"&" * 200, b"{}",
     b"--x\r\nContent-Disposition: form-data; name=token\r\n\r\nabc\r\n--x--\r\n"]))


def _request(t: Target, method: str, target: str, credential: str, extra: list,
             content_type: str | None, encoding: str | None, body: bytes, chunked: bool,
             host: str | None) -> bytes:
    lines = [f"{method} {target} HTTP/1.1", "Connection: close"]
    lines.append(f"Host: {host if host is not None else f'127.0.0.1:{t.port}'}")
    cred = {"bearer": f"Authorization: Bearer {TOKEN}",
            "bearer-wrong": f"Authorization: Bearer {TOKEN[:-1]}?",
            "bearer-empty": "Authorization: Bearer ", "basic": "Authorization: Basic eDp5",
            "cookie": f"Cookie: {COOKIE}={t.cookie}\r\nX-CSRF-Token: {t.csrf}",
            "cookie-wrong": f"Cookie: {COOKIE}={t.cookie[:-2]}xx"}.get(credential)
    if cred:
        lines.append(cred)
    lines += [f"{k}: {v}" for k, v in extra]
    if content_type:
        lines.append(f"Content-Type: {content_type}")
    if encoding:
        lines.append(f"Content-Encoding: {encoding}")
    if chunked:
        lines.append("Transfer-Encoding: chunked")
        payload = (b"%x\r\n%s\r\n" % (len(body), body) if body else b"") + b"0\r\n\r\n"
    else:
        lines.append(f"Content-Length: {len(body)}")
        payload = body
    return "\r\n".join(lines).encode("latin-1") + b"\r\n\r\n" + payload


def _status(port: int, raw: bytes) -> int:
    """The status code of the answer. Read until the server closes (so whatever it logs about
    this request is logged by then), except an event stream, which never ends."""
    with socket.create_connection(("127.0.0.1", port), timeout=20) as s:
        s.sendall(raw)
        answer = b""
        while chunk := s.recv(65536):
            answer += chunk
            if b"\r\n\r\n" in answer and b"text/event-stream" in answer.split(b"\r\n\r\n")[0]:
                break
    assert answer.startswith(b"HTTP/1."), answer[:100]
    return int(answer.split(b" ", 2)[1])


def _check_logs(t: Target) -> None:
    bad = [r for r in t.records.records if r.exc_info or r.levelno >= logging.ERROR]
    assert not bad, [(r.name, r.getMessage()) for r in bad]


@settings(max_examples=150, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(method=METHOD, path=PATH, query=QUERY, credential=CREDENTIAL, extra=EXTRA,
       content_type=CONTENT_TYPE, encoding=ENCODING, body=BODY, chunked=st.booleans(),
       host=st.one_of(st.none(), st.none(), st.none(), HEADER_VALUE))
def test_random_requests(target, method, path, query, credential, extra, content_type,
                         encoding, body, chunked, host):
    target.records.records.clear()  # what is logged from here on is this example's doing
    code = _status(target.port, _request(target, method, path + query, credential, extra,
                                          content_type, encoding, body, chunked, host))
    assert code != 500 and code < 600, code
    authenticated = credential in ("bearer", "cookie")
    # The rest may see the login page and the style sheet, and be sent to /login: nothing else.
    if not authenticated and path.split("?")[0] not in PUBLIC:
        assert not 200 <= code < 300 or code == 302, (method, path, code)
    logged_in = method == "POST" and path == "/login" and TOKEN.encode() in body
    if not authenticated and not logged_in:
        assert code != 303  # a session cookie handed out for a wrong token
    _check_logs(target)


@settings(max_examples=60, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(raw=st.one_of(st.binary(min_size=1, max_size=200),
                     st.lists(st.sampled_from([b"GET", b" ", b"/", b"api/status", b"HTTP/1.1",
                                               b"\r\n", b"Host: 127.0.0.1", b":", b"\x00",
                                               b"Content-Length: 5", b"\xff", b"HTTP/2.0",
                                               b"Transfer-Encoding: chunked", b"0\r\n"]),
                              min_size=1, max_size=25).map(b"".join)))
def test_random_bytes(target, raw):
    """Arbitrary bytes ending a request head: an answer (400, 421, 401 …) or a close, no 500."""
    target.records.records.clear()
    with socket.create_connection(("127.0.0.1", target.port), timeout=20) as s:
        s.sendall(raw + b"\r\n\r\n")
        s.shutdown(socket.SHUT_WR)
        answer = b""
        while chunk := s.recv(4096):
            answer += chunk
    if answer:
        assert answer.startswith(b"HTTP/1."), answer[:100]
        assert int(answer.split(b" ", 2)[1]) != 500
        assert not answer.split(b" ", 2)[1].startswith(b"2"), answer[:200]
    _check_logs(target)
