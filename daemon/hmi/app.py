"""The operator web page served by the daemon (aiohttp): status, live progress (SSE), Start,
Abort, last verdict, history and reports, behind a token.

Auth: ``Authorization: Bearer <token>`` (scripts) or a login form that sets an HttpOnly,
SameSite=Strict (and, over TLS, Secure) signed session cookie that survives a daemon restart
(``daemon.hmi.auth``); tokens are compared in constant time. Cookie-authenticated POSTs also
need the per-session CSRF token (header ``X-CSRF-Token``) and a same-origin ``Origin``.
Reports are looked up by run id in the store, never by a path from the request.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import json
from collections.abc import Awaitable, Callable, Mapping
from importlib import resources
from typing import Any

from aiohttp import web

from daemon.hmi.auth import SESSION_TTL_S, Auth
from daemon.session import Refused, Session
from daemon.store import Store, StoreError

COOKIE = "rumba_session"
LOGIN_FAIL_DELAY_S = 0.5  # slows token guessing; the token has ≥ 16 characters anyway
SSE_KEEPALIVE_S = 15.0
CSP = ("default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' data:; "
       "connect-src 'self'; form-action 'self'; frame-ancestors 'none'; base-uri 'none'")
REPORT_CSP = "default-src 'none'; style-src 'unsafe-inline'; img-src data:"
PUBLIC = {"/login", "/hmi.css"}

SESSIONS_KEY = web.AppKey("sessions", dict)
STORE_KEY = web.AppKey("store", Store)
AUTH_KEY = web.AppKey("auth", object)
STREAMS_KEY = web.AppKey("streams", set)
VIA_KEY = web.RequestKey("via", str)
CSRF_KEY = web.RequestKey("csrf", str)


def _asset(name: str) -> str:
    return resources.files("daemon.hmi").joinpath(name).read_text(encoding="utf-8")


@web.middleware
async def security(request: web.Request, handler: Callable[[web.Request], Awaitable]
                   ) -> web.StreamResponse:
    auth: Auth = request.app[AUTH_KEY]  # type: ignore[assignment]
    if request.path not in PUBLIC:
        header = request.headers.get("Authorization", "")
        csrf = auth.session(request.cookies.get(COOKIE))
        if header.startswith("Bearer ") and auth.token_ok(header[7:].strip()):
            request[VIA_KEY] = "bearer"  # not sent by browsers on their own: no CSRF risk
        elif csrf is not None:
            request[VIA_KEY] = "cookie"
            request[CSRF_KEY] = csrf
            if request.method not in ("GET", "HEAD"):
                origin = request.headers.get("Origin")
                if origin is not None and origin != f"{request.scheme}://{request.host}":
                    raise web.HTTPForbidden(text="cross-origin request refused")
                sent = request.headers.get("X-CSRF-Token", "")
                if not hmac.compare_digest(sent.encode(), csrf.encode()):
                    raise web.HTTPForbidden(text="missing or wrong CSRF token")
        elif request.path.startswith("/api/") or request.method != "GET":
            raise web.HTTPUnauthorized(text="token required",
                                       headers={"WWW-Authenticate": "Bearer"})
        else:
            raise web.HTTPFound("/login")
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
    form = await request.post()
    if not auth.token_ok(str(form.get("token", ""))):
        await asyncio.sleep(LOGIN_FAIL_DELAY_S)
        return web.Response(status=401, content_type="text/html", text=_asset(
            "login.html").replace("{{error}}", '<p class="error">Wrong token.</p>'))
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
    html = _asset("index.html").replace("{{csrf}}", request.get(CSRF_KEY) or "")
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
    return {"id": r.id, "machine": r.machine, "trigger": r.trigger, "state": r.state,
            "reason": r.reason, "verdict": r.verdict, "summary": r.summary, "hits": r.hits,
            "touch_total": r.touch_total, "started_at": r.started_at, "ended_at": r.ended_at,
            "report": f"/reports/{r.id}.html" if store.report(r.id) else None}


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


async def runs(request: web.Request) -> web.Response:
    store = request.app[STORE_KEY]
    machine = request.query.get("machine")
    try:
        limit = min(int(request.query.get("limit", "20")), 500)
    except ValueError:
        raise web.HTTPBadRequest(text="limit must be an integer") from None
    return web.json_response([_run_dict(r, store) for r in store.runs(machine, limit)])


async def report_file(request: web.Request) -> web.StreamResponse:
    store = request.app[STORE_KEY]
    run_id, kind = request.match_info["run_id"], request.match_info["kind"]
    try:
        paths = store.report(run_id)
    except StoreError:
        paths = None
    if paths is None:
        raise web.HTTPNotFound(text=f"no report for run {run_id!r}")
    path = paths[0] if kind == "html" else paths[1]
    if not path.is_file():
        raise web.HTTPNotFound(text=f"report file of run {run_id} is missing")
    resp = web.FileResponse(path, headers={
        "Content-Type": "text/html; charset=utf-8" if kind == "html" else "application/json"})
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
               secure_cookie: bool = False, secret: bytes | None = None) -> web.Application:
    """``secret``: the session signing secret (``auth.load_or_create_secret``); without it
    sessions end with this app."""
    app = web.Application(middlewares=[security], client_max_size=64 * 1024)
    app[SESSIONS_KEY] = dict(sessions)
    app[STORE_KEY] = store
    app[AUTH_KEY] = Auth(token, secure_cookie, secret=secret, store=store)
    app[STREAMS_KEY] = set()

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
    app.router.add_get("/reports/{run_id:[A-Za-z0-9_.-]{1,64}}.{kind:html|json}", report_file)
    return app
