"""The operator web page served by the daemon (aiohttp): status, live progress (SSE), Start,
Abort, last verdict, history and reports, behind a token.

Auth: ``Authorization: Bearer <token>`` (scripts) or a login form that sets an HttpOnly,
SameSite=Strict (and, over TLS, Secure) signed session cookie that survives a daemon restart
(``daemon.hmi.auth``); tokens are compared in constant time. Cookie-authenticated POSTs also
need the per-session CSRF token (header ``X-CSRF-Token``) and an allowed ``Origin``. Every
request needs an allowed ``Host`` (DNS rebinding); wrong tokens are limited daemon-wide, and
headers, bodies and query values are bounded (``daemon.hmi.limits``). Reports are looked up by
a validated run id in the store, never by a path from the request.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import json
from collections.abc import Awaitable, Callable, Iterable, Mapping
from html import escape
from importlib import resources
from typing import Any
from urllib.parse import parse_qsl

from aiohttp import web

from daemon.hmi.auth import SESSION_TTL_S, Auth
from daemon.hmi.limits import AuthLimiter, HmiLimits, Origins, int_param
from daemon.hmi.trend_api import trend_handler
from daemon.session import Refused, Session
from daemon.store import Store, StoreError, validate_run_id
from daemon.verdict_text import ADVICE

COOKIE = "rumba_session"
SSE_KEEPALIVE_S = 15.0
CSP = ("default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' data:; "
       "connect-src 'self'; form-action 'self'; frame-ancestors 'none'; base-uri 'none'")
REPORT_CSP = "default-src 'none'; style-src 'unsafe-inline'; img-src data:"
REPORT_TYPES = {"html": "text/html; charset=utf-8", "json": "application/json",
                "pdf": "application/pdf"}  # the PDF lies beside the HTML (report.pdf_path)
PUBLIC = {"/login", "/hmi.css"}

SESSIONS_KEY = web.AppKey("sessions", dict)
STORE_KEY = web.AppKey("store", Store)
AUTH_KEY = web.AppKey("auth", object)
STREAMS_KEY = web.AppKey("streams", set)
LIMITS_KEY = web.AppKey("limits", HmiLimits)
LIMITER_KEY = web.AppKey("limiter", AuthLimiter)
ORIGINS_KEY = web.AppKey("origins", Origins)
PAGE_KEY = web.AppKey("page", str)  # the page's settings, HTML-escaped JSON for its <meta>
VIA_KEY = web.RequestKey("via", str)
CSRF_KEY = web.RequestKey("csrf", str)


def _asset(name: str) -> str:
    return resources.files("daemon.hmi").joinpath(name).read_text(encoding="utf-8")


def _local(request: web.Request) -> tuple[str, int]:
    """The (address, port) the client connected to: the port is only known once listening."""
    sock = request.transport.get_extra_info("sockname") if request.transport else None
    if not isinstance(sock, tuple) or len(sock) < 2:
        raise web.HTTPBadRequest(text="connection closed")
    return str(sock[0]), int(sock[1])


def _locked_out(request: web.Request) -> None:
    """429 (token not looked at) while this client or everybody is locked out."""
    wait = request.app[LIMITER_KEY].retry_after(request.remote)
    if wait > 0:
        raise web.HTTPTooManyRequests(
            text=f"too many wrong tokens: try again in {wait:.0f} s",
            headers={"Retry-After": str(max(1, round(wait)))})


def _origin_ok(request: web.Request) -> bool:
    """A state-changing request comes from the HMI's own pages (or a script): Origin one of
    the allowed origins, and the browser's fetch metadata, which pages cannot forge, not
    cross-site. Under ``Referrer-Policy: no-referrer`` Chromium sends ``Origin: null`` with the
    page's own form posts: accepted only with ``Sec-Fetch-Site: same-origin``."""
    site = request.headers.get("Sec-Fetch-Site")
    if site in ("cross-site", "same-site"):
        return False
    origin = request.headers.get("Origin")
    if origin is None:  # scripts, old browsers: the CSRF token still has to be right
        return True
    if origin == "null":
        return site == "same-origin"
    return request.app[ORIGINS_KEY].origin_ok(origin, _local(request), request.scheme)


def _authenticate(request: web.Request) -> None:
    """Bearer token or session cookie (+ CSRF, Origin), else 401 / 403 / 429 / redirect."""
    auth: Auth = request.app[AUTH_KEY]  # type: ignore[assignment]
    header = request.headers.get("Authorization", "")
    if header.startswith("Bearer "):
        _locked_out(request)
        limiter = request.app[LIMITER_KEY]
        if not auth.token_ok(header[7:].strip()):
            limiter.failed(request.remote, "bearer")
            raise web.HTTPUnauthorized(text="wrong token", headers={"WWW-Authenticate": "Bearer"})
        limiter.succeeded(request.remote)
        request[VIA_KEY] = "bearer"  # not sent by browsers on their own: no CSRF risk
        return
    # A cookie is signed with a 256-bit key: a wrong one is not a token guess (and expired
    # ones come from honest browsers), so it is not counted and works during a lockout.
    csrf = auth.session(request.cookies.get(COOKIE))
    if csrf is not None:
        request[VIA_KEY] = "cookie"
        request[CSRF_KEY] = csrf
        if request.method not in ("GET", "HEAD"):
            if not _origin_ok(request):
                raise web.HTTPForbidden(text="cross-origin request refused")
            sent = request.headers.get("X-CSRF-Token", "")
            if not hmac.compare_digest(sent.encode(), csrf.encode()):
                raise web.HTTPForbidden(text="missing or wrong CSRF token")
    elif request.path.startswith("/api/") or request.method != "GET":
        raise web.HTTPUnauthorized(text="token required", headers={"WWW-Authenticate": "Bearer"})
    else:
        raise web.HTTPFound("/login")


async def _read_body(request: web.Request) -> None:
    """Read the whole body now, within the body timeout (aiohttp has none) and the size cap;
    handlers then get it from the request's cache."""
    try:
        async with asyncio.timeout(request.app[LIMITS_KEY].body_timeout_s):
            await request.read()
    except TimeoutError:
        raise web.HTTPRequestTimeout(text="request body too slow",
                                     headers={"Connection": "close"}) from None
    except web.HTTPException:
        raise  # 413 from the size cap
    except (web.RequestPayloadError, ConnectionError, ValueError) as e:  # bad chunks, cut body
        raise web.HTTPBadRequest(text=f"bad request body: {e}",
                                 headers={"Connection": "close"}) from None


@web.middleware
async def security(request: web.Request, handler: Callable[[web.Request], Awaitable]
                   ) -> web.StreamResponse:
    # DNS rebinding: a page of evil.example whose name now points here would be same-origin
    # for the browser; its requests still say "Host: evil.example".
    if not request.app[ORIGINS_KEY].host_ok(request.headers.get("Host"), _local(request),
                                            request.scheme):
        raise web.HTTPMisdirectedRequest(text="unknown Host; add it to hmi.public_origins")
    if request.path not in PUBLIC:
        _authenticate(request)
    if request.body_exists:
        if request.headers.get("Content-Encoding", "identity").lower() != "identity":
            raise web.HTTPUnsupportedMediaType(text="compressed request bodies are not accepted",
                                               headers={"Connection": "close"})
        await _read_body(request)
    resp = await handler(request)
    if resp.prepared:  # a stream (SSE) set its own headers before sending them
        return resp
    resp.headers.setdefault("Content-Security-Policy", CSP)
    resp.headers["X-Content-Type-Options"] = "nosniff"
    resp.headers["X-Frame-Options"] = "DENY"
    resp.headers["Referrer-Policy"] = "no-referrer"
    resp.headers.setdefault("Cache-Control", "no-store")
    return resp


# ------------------------------------------------------------------------------------ pages


async def login_page(request: web.Request) -> web.Response:
    return web.Response(text=_asset("login.html").replace("{{error}}", ""),
                        content_type="text/html")


async def login(request: web.Request) -> web.Response:
    auth: Auth = request.app[AUTH_KEY]  # type: ignore[assignment]
    if not _origin_ok(request):  # login CSRF: signing a victim in from another site
        raise web.HTTPForbidden(text="cross-origin request refused")
    if request.content_type != "application/x-www-form-urlencoded":
        raise web.HTTPUnsupportedMediaType(text="send the login form (urlencoded)")
    try:
        form = dict(parse_qsl((await request.read()).decode("utf-8", "replace"),
                              keep_blank_values=True, max_num_fields=8))
    except ValueError:
        raise web.HTTPBadRequest(text="too many form fields") from None
    _locked_out(request)
    limiter = request.app[LIMITER_KEY]
    if not auth.token_ok(form.get("token", "")):
        limiter.failed(request.remote, "login")
        return web.Response(status=401, content_type="text/html", text=_asset(
            "login.html").replace("{{error}}", '<p class="error">Wrong token.</p>'))
    limiter.succeeded(request.remote)
    cookie, _ = auth.new_session()
    resp = web.HTTPSeeOther("/")
    resp.set_cookie(COOKIE, cookie, httponly=True, samesite="Strict", secure=auth.secure_cookie,
                    max_age=SESSION_TTL_S, path="/")
    raise resp


async def logout(request: web.Request) -> web.Response:
    auth: Auth = request.app[AUTH_KEY]  # type: ignore[assignment]
    auth.revoke(request.cookies.get(COOKIE))
    resp = web.json_response({"ok": True})
    resp.del_cookie(COOKIE, path="/")
    return resp


async def index(request: web.Request) -> web.Response:
    html = _asset("index.html").replace("{{csrf}}", request.get(CSRF_KEY) or "").replace(
        "{{config}}", request.app[PAGE_KEY])
    return web.Response(text=html, content_type="text/html")


async def asset(request: web.Request) -> web.Response:
    name = request.match_info["name"]
    types = {"hmi.js": "application/javascript", "hmi.css": "text/css"}
    return web.Response(text=_asset(name), content_type=types[name],
                        headers={"Cache-Control": "no-cache"})


# -------------------------------------------------------------------------------------- API


def _sessions(request: web.Request) -> Mapping[str, Session]:
    return request.app[SESSIONS_KEY]


def _session(request: web.Request) -> Session:
    name = request.match_info["machine"]
    s = _sessions(request).get(name)
    if s is None:
        raise web.HTTPNotFound(text=f"no machine {name!r}")
    return s


def _run_dict(r: Any, store: Store) -> dict[str, Any]:
    paths = store.report(r.id)
    pdf = paths is not None and paths[0].with_suffix(".pdf").is_file()
    return {"id": r.id, "machine": r.machine, "trigger": r.trigger, "state": r.state,
            "reason": r.reason, "verdict": r.verdict, "summary": r.summary, "hits": r.hits,
            "touch_total": r.touch_total, "started_at": r.started_at, "ended_at": r.ended_at,
            "report": f"/reports/{r.id}.html" if paths else None,
            "pdf": f"/reports/{r.id}.pdf" if pdf else None}


async def status(request: web.Request) -> web.Response:
    return web.json_response({n: s.status() for n, s in _sessions(request).items()})


async def start(request: web.Request) -> web.Response:
    s = _session(request)
    # Scripts (`rumba verify --daemon`, bearer token) say who they are; the page is "hmi".
    trigger = "cli" if request.get(VIA_KEY) == "bearer" and \
        request.query.get("trigger") == "cli" else "hmi"
    try:
        run_id = s.start(trigger)
    except Refused as e:
        return web.json_response({"error": str(e)}, status=409)
    return web.json_response({"run_id": run_id}, status=202)


async def abort(request: web.Request) -> web.Response:
    s = _session(request)
    if not await s.abort("hmi"):
        return web.json_response({"error": f"{s.setup.name}: nothing to abort"}, status=409)
    return web.json_response(s.status())


# Query values are bounded before any use (limits.int_param): outside, 400 with the reason.
MAX_RUNS = 500


def run_id_ok(run_id: str) -> bool:
    """Whether ``run_id`` has the run-id form (the store's own check, before it is asked)."""
    try:
        validate_run_id(run_id)
    except StoreError:
        return False
    return True


async def runs(request: web.Request) -> web.Response:
    store = request.app[STORE_KEY]
    machine = request.query.get("machine")
    if machine is not None and not 0 < len(machine) <= 64:
        raise web.HTTPBadRequest(text="machine must be a machine name (1 to 64 characters)")
    limit = int_param(request, "limit", 20, 1, MAX_RUNS)
    return web.json_response([_run_dict(r, store) for r in store.runs(machine, limit)])


async def report_file(request: web.Request) -> web.StreamResponse:
    store = request.app[STORE_KEY]
    run_id, kind = request.match_info["run_id"], request.match_info["kind"]
    if not run_id_ok(run_id):
        raise web.HTTPNotFound(text="no such run")
    try:
        paths = store.report(run_id)
    except StoreError:
        paths = None
    if paths is None:
        raise web.HTTPNotFound(text=f"no report for run {run_id!r}")
    path = {"html": paths[0], "json": paths[1], "pdf": paths[0].with_suffix(".pdf")}[kind]
    if not path.is_file():
        raise web.HTTPNotFound(text=f"report file of run {run_id} is missing")
    resp = web.FileResponse(path, headers={"Content-Type": REPORT_TYPES[kind]})
    if kind == "pdf":
        resp.headers["Content-Disposition"] = f'inline; filename="rumba-{run_id}.pdf"'
    resp.headers["Content-Security-Policy"] = REPORT_CSP
    return resp


async def events(request: web.Request) -> web.StreamResponse:
    """Server-sent events: one ``status`` event per session change (and a keep-alive)."""
    resp = web.StreamResponse(headers={"Content-Type": "text/event-stream",
                                       "Cache-Control": "no-store",
                                       "Content-Security-Policy": CSP})
    await resp.prepare(request)
    merged: asyncio.Queue = asyncio.Queue()
    subs = [(s, s.subscribe()) for s in _sessions(request).values()]

    async def pump(q: asyncio.Queue) -> None:
        while True:
            await merged.put(await q.get())

    pumps = [asyncio.create_task(pump(q)) for _, q in subs]
    streams = request.app[STREAMS_KEY]
    me = asyncio.current_task()
    streams.add(me)
    try:
        while True:
            try:
                st = await asyncio.wait_for(merged.get(), SSE_KEEPALIVE_S)
                await resp.write(f"event: status\ndata: {json.dumps(st)}\n\n".encode())
            except TimeoutError:
                await resp.write(b": keep-alive\n\n")
    except (ConnectionResetError, asyncio.CancelledError):
        pass
    finally:
        streams.discard(me)
        for t in pumps:
            t.cancel()
        for s, q in subs:
            s.unsubscribe(q)
        with contextlib.suppress(Exception):
            await resp.write_eof()
    return resp


def create_app(sessions: Mapping[str, Session], store: Store, token: str,
               secure_cookie: bool = False, secret: bytes | None = None, *,
               limits: HmiLimits | None = None, bind_host: str | None = None,
               public_origins: Iterable[str] = (), stale_after_h: float = 24.0
               ) -> web.Application:
    """``secret``: the session signing secret (``auth.load_or_create_secret``); without it
    sessions end with this app. ``bind_host`` (``hmi.host``) and ``public_origins``
    (``scheme://name[:port]`` the operators type) are accepted as Host / Origin besides the
    address the client connected to (and localhost names on loopback). The timeouts and
    sizes of ``limits`` apply to any ``web.AppRunner`` of this app (``handler_args``); a verdict
    older than ``stale_after_h`` is flagged stale on the page."""
    limits = limits or HmiLimits()
    app = web.Application(middlewares=[security], client_max_size=limits.max_body_bytes,
                          handler_args=limits.server_args())
    app[SESSIONS_KEY] = dict(sessions)
    app[STORE_KEY] = store
    app[AUTH_KEY] = Auth(token, secure_cookie, secret=secret, store=store)
    app[LIMITS_KEY] = limits
    app[LIMITER_KEY] = AuthLimiter(limits)
    app[ORIGINS_KEY] = Origins(bind_host, public_origins)
    app[STREAMS_KEY] = set()
    app[PAGE_KEY] = escape(json.dumps({"stale_after_h": stale_after_h, "advice": ADVICE}))

    async def end_streams(app: web.Application) -> None:
        # Open event streams never end on their own: close them so shutdown is immediate.
        for task in list(app[STREAMS_KEY]):
            task.cancel()

    app.on_shutdown.append(end_streams)
    app.router.add_get("/login", login_page)
    app.router.add_post("/login", login)
    app.router.add_post("/logout", logout)
    app.router.add_get("/", index)
    app.router.add_get("/{name:hmi\\.(?:js|css)}", asset)
    app.router.add_get("/api/status", status)
    app.router.add_get("/api/events", events)
    app.router.add_get("/api/runs", runs)
    app.router.add_post("/api/machines/{machine}/start", start)
    app.router.add_post("/api/machines/{machine}/abort", abort)
    app.router.add_get("/api/machines/{machine}/trend",
                       trend_handler(SESSIONS_KEY, STORE_KEY))
    app.router.add_get("/reports/{run_id:[A-Za-z0-9_.-]{1,64}}.{kind:html|json|pdf}",
                       report_file)
    return app
