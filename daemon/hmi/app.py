"""The operator web page served by the daemon (aiohttp): status, live progress (SSE), Start,
Abort, last verdict, history, reports and compensation, behind a token.

Access (token, login form, session cookie, CSRF, Host / Origin, bounded requests) is
``daemon.hmi.access``, shared with the fleet page. Reports are looked up by a validated run id
in the store, never by a path from the request.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import Iterable, Mapping
from html import escape
from typing import Any

from aiohttp import web

from daemon.analysis.verdict_text import ADVICE
from daemon.hmi.access import (  # the access names are re-exported: callers import them here
    AUTH_KEY,
    COOKIE,
    CSP,
    CSRF_KEY,
    HMI_NAME,
    IDENTITY_KEY,
    LIMITER_KEY,
    LIMITS_KEY,
    ORIGINS_KEY,
    PUBLIC,
    VIA_KEY,
    asset,
    page_asset,
    require,
    secured_app,
)
from daemon.hmi.auth import Auth, Identity
from daemon.hmi.baseline_api import add_routes as add_baseline_routes
from daemon.hmi.compensation_api import add_routes as add_compensation_routes
from daemon.hmi.limits import HmiLimits, int_param
from daemon.hmi.map_api import add_routes as add_map_routes
from daemon.hmi.trend_api import trend_handler
from daemon.hmi.users import Accounts
from daemon.reports.index_scatter import index_scatter_doc
from daemon.reports.temperatures import temperature_lines
from daemon.run.session import Refused, Session
from daemon.store import report_jobs
from daemon.store.actions import record_action
from daemon.store.journal import Store, StoreError, validate_run_id

__all__ = ["AUTH_KEY", "COOKIE", "LIMITER_KEY", "LIMITS_KEY", "ORIGINS_KEY", "PUBLIC",
           "REPORT_CSP", "SESSIONS_KEY", "STORE_KEY", "asset", "create_app", "run_id_ok"]

SSE_KEEPALIVE_S = 15.0
REPORT_CSP = "default-src 'none'; style-src 'unsafe-inline'; img-src data:"
REPORT_TYPES = {"html": "text/html; charset=utf-8", "json": "application/json",
                "pdf": "application/pdf"}  # the PDF lies beside the HTML (report.pdf_path)

SESSIONS_KEY = web.AppKey("sessions", dict)
STORE_KEY = web.AppKey("store", Store)
STREAMS_KEY = web.AppKey("streams", set)
PAGE_KEY = web.AppKey("page", str)  # the page's settings, HTML-escaped JSON for its <meta>


# ------------------------------------------------------------------------------------ pages


async def index(request: web.Request) -> web.Response:
    html = page_asset("index.html").replace("{{csrf}}", request.get(CSRF_KEY) or "").replace(
        "{{config}}", request.app[PAGE_KEY])
    return web.Response(text=html, content_type="text/html")


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
    job = report_jobs.get(store, r.id)  # migration 10: the report's end, not the run's reason
    return {"id": r.id, "machine": r.machine, "trigger": r.trigger, "state": r.state,
            "report_state": job.state if job else None,
            "report_error": job.reason if job and job.state == report_jobs.FAILED else "",
            "reason": r.reason, "verdict": r.verdict, "summary": r.summary, "hits": r.hits,
            "started_by": r.started_by,
            "touch_total": r.touch_total, "started_at": r.started_at, "ended_at": r.ended_at,
            "report": f"/reports/{r.id}.html" if paths else None,
            "pdf": f"/reports/{r.id}.pdf" if pdf else None}


async def status(request: web.Request) -> web.Response:
    return web.json_response({n: s.status() for n, s in _sessions(request).items()})


# Start from the page asks for this pre-flight list, every item ticked: a run that
# starts with the probe in the magazine or a door open is a crash or a wasted hour.
PREFLIGHT = (("probe", "Touch probe in the spindle, switched on"),
             ("balls", "Balls clean and tight on their stems, artefact clamped"),
             ("doors", "Doors closed"),
             ("area", "Working area clear: no tools, clamps, chips or people inside"))


def _identity(request: web.Request) -> Identity:
    return request.get(IDENTITY_KEY) or Identity("token", "admin", "bearer")


def _journal(request: web.Request, machine: str, action: str, outcome: str, *,
             run_id: str = "", detail: str = "") -> None:
    i = _identity(request)
    record_action(request.app[STORE_KEY], machine, action, i.name, i.role, i.via, outcome,
                  run_id=run_id, detail=detail)


async def _preflight(request: web.Request) -> str:
    """The ticked pre-flight list of a page's start request ('' for scripts), else 400."""
    if request.get(VIA_KEY) == "bearer":
        return ""
    try:
        body = json.loads(await request.text() or "{}")
    except (ValueError, UnicodeDecodeError):
        body = None
    ticked = body.get("preflight") if isinstance(body, dict) else None
    missing = [k for k, _ in PREFLIGHT if not isinstance(ticked, list) or k not in ticked]
    if missing:
        raise web.HTTPBadRequest(text="pre-flight checklist not confirmed: " + "; ".join(
            t for k, t in PREFLIGHT if k in missing))
    return "pre-flight ticked: " + ", ".join(k for k, _ in PREFLIGHT)


async def start(request: web.Request) -> web.Response:
    s = _session(request)
    require(request, "operator", "starting a run")
    # Scripts (`rumba verify --daemon`, bearer token) say who they are; the page is "hmi".
    trigger = "cli" if request.get(VIA_KEY) == "bearer" and \
        request.query.get("trigger") == "cli" else "hmi"
    checked = await _preflight(request)
    person = _identity(request).name if _identity(request).via == "password" else ""
    named = _operator(request)  # `rumba verify --daemon --operator NAME`
    if isinstance(named, web.Response):
        return named
    if named:
        person, checked = named, f"operator named by the script: {named}"
    try:
        run_id = s.start(trigger, started_by=person)
    except Refused as e:
        _journal(request, s.setup.name, "start", f"refused: {e}", detail=checked)
        return web.json_response({"error": str(e)}, status=409)
    _journal(request, s.setup.name, "start", "ok", run_id=run_id, detail=checked)
    return web.json_response({"run_id": run_id}, status=202)


def _operator(request: web.Request) -> str | web.Response:
    """The person a script with the bearer token names (``?operator=``), checked by the
    journal's rules for a name; '' when none, a 400 answer when refused."""
    name = request.query.get("operator")
    if name is None:
        return ""
    if request.get(VIA_KEY) != "bearer":
        return web.json_response({"error": "operator: for scripts with the bearer token only "
                                           "(a signed-in person starts as themselves)"},
                                 status=400)
    from daemon.compensation.names import BadName, validate_by

    try:
        return validate_by(name, "operator", allow_unattended=False)
    except BadName as e:
        return web.json_response({"error": str(e)}, status=400)


async def me(request: web.Request) -> web.Response:
    """Who is signed in, and what the page may offer them."""
    i = _identity(request)
    return web.json_response({"name": i.name, "role": i.role, "via": i.via,
                              "may_compensate": i.may("engineer")})


# `rumba verify --daemon` stopped by a signal names it (bearer scripts only); a fixed text per
# value, so nothing a client sends reaches the journal's reason
ABORT_BY = {"SIGINT": "Ctrl-C (SIGINT) on rumba verify --daemon",
            "SIGTERM": "SIGTERM on rumba verify --daemon"}


async def abort(request: web.Request) -> web.Response:
    """Abort the machine's run; answers once it has ended (controller reset, journal row) with
    the final status. ``run_id``: only that run (a script never stops a run it did not start)."""
    s = _session(request)
    by, run_id = request.query.get("by"), request.query.get("run_id")
    if by is not None and (by not in ABORT_BY or request.get(VIA_KEY) != "bearer"):
        return web.json_response({"error": f"by: expected one of {', '.join(ABORT_BY)} "
                                           "(scripts with the bearer token only)"}, status=400)
    if run_id is not None and (run_id != s.run_id or not s.busy):
        return web.json_response({"error": f"{s.setup.name}: run {run_id[:64]!r} is not "
                                           "running", **s.status()}, status=409)
    require(request, "operator", "aborting a run")
    person = f"{_identity(request).name} (hmi)" if _identity(request).via == "password" \
        else "hmi"
    current = s.run_id or ""
    if not await s.abort(ABORT_BY[by] if by else person):
        _journal(request, s.setup.name, "abort", "refused: nothing to abort")
        return web.json_response({"error": f"{s.setup.name}: nothing to abort"}, status=409)
    _journal(request, s.setup.name, "abort", "ok", run_id=current, detail=by or "")
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


async def run_detail(request: web.Request) -> web.Response:
    """One run: its record and what its analysis says beyond the verdict — the rotary axes'
    indexing repeatability behind the link u (the report's own text) and the
    temperature channels; ``index_scatter`` null when the run has no analysis."""
    store = request.app[STORE_KEY]
    run_id = request.match_info["run_id"]
    if not run_id_ok(run_id):
        raise web.HTTPNotFound(text="no such run")
    try:
        row = store.run(run_id)
        analysis = store.analysis(run_id)
    except StoreError:
        raise web.HTTPNotFound(text=f"no run {run_id!r}") from None
    out = _run_dict(row, store)
    out["index_scatter"] = index_scatter_doc(analysis) if analysis else None
    out["temperatures"] = temperature_lines(analysis) if analysis else []
    return web.json_response(out)


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
               public_origins: Iterable[str] = (), stale_after_h: float = 24.0,
               accounts: Accounts | None = None) -> web.Application:
    """``secret``: the session signing secret (``auth.load_or_create_secret``); without it
    sessions end with this app. ``bind_host`` (``hmi.host``) and ``public_origins``
    (``scheme://name[:port]`` the operators type) are accepted as Host / Origin besides the
    address the client connected to (and localhost names on loopback). The timeouts and
    sizes of ``limits`` apply to any ``web.AppRunner`` of this app (``handler_args``); a verdict
    older than ``stale_after_h`` is flagged stale on the page. ``accounts``: people sign in
    with name and password and act in their role (``daemon.hmi.users``)."""
    app = secured_app(Auth(token, secure_cookie, secret=secret, store=store,
                           accounts=accounts), limits, bind_host, public_origins, HMI_NAME)
    app[SESSIONS_KEY] = dict(sessions)
    app[STORE_KEY] = store
    app[STREAMS_KEY] = set()
    app[PAGE_KEY] = escape(json.dumps({"stale_after_h": stale_after_h, "advice": ADVICE,
                                       "preflight": PREFLIGHT}))

    async def end_streams(app: web.Application) -> None:
        # Open event streams never end on their own: close them so shutdown is immediate.
        for task in list(app[STREAMS_KEY]):
            task.cancel()

    app.on_shutdown.append(end_streams)
    app.router.add_get("/", index)
    app.router.add_get("/{name:hmi\\.js}", asset)  # hmi.css: secured_app (the login's too)
    app.router.add_get("/api/status", status)
    app.router.add_get("/api/me", me)
    app.router.add_get("/api/events", events)
    app.router.add_get("/api/runs", runs)
    app.router.add_get("/api/runs/{run_id:[A-Za-z0-9_.-]{1,64}}", run_detail)
    app.router.add_post("/api/machines/{machine}/start", start)
    app.router.add_post("/api/machines/{machine}/abort", abort)
    app.router.add_get("/api/machines/{machine}/trend",
                       trend_handler(SESSIONS_KEY, STORE_KEY))
    add_compensation_routes(app, SESSIONS_KEY, STORE_KEY)  # confirm from the page
    add_baseline_routes(app, SESSIONS_KEY, STORE_KEY)  # the drift baseline
    add_map_routes(app, STORE_KEY, REPORT_CSP)  # maps of the linear axes
    app.router.add_get("/reports/{run_id:[A-Za-z0-9_.-]{1,64}}.{kind:html|json|pdf}",
                       report_file)
    return app
