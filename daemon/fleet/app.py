"""The fleet page (aiohttp, read-only over the PostgreSQL fleet store): every machine's last
verdict with date, age and stale flag, a machine's per-link trend and runs, and its reports.

Authentication, login, Host / Origin checks and request limits are the HMI's own
(``daemon.hmi.access.secured_app``: its ``security`` middleware and login handlers), so the
two pages behave alike: ``Authorization: Bearer <token>`` for scripts, a signed session
cookie after the login form for browsers. Reports: the store holds the path each daemon
wrote its report to; the page serves that file only if it resolves (symlinks followed)
inside one of the ``reports_dirs`` it was given (a fleet service on the daemons' host, or
with their report directories mounted read-only); otherwise the link answers 404 naming the
host path. A run id from the URL is validated before it is looked up; no path ever comes
from a request.
"""

from __future__ import annotations

import contextlib
import logging
import re
import time
from collections.abc import Awaitable, Callable, Iterable, Sequence
from importlib import resources
from pathlib import Path
from typing import Any

import psycopg
from aiohttp import web

from contracts.setup_types import SAFE_NAME
from daemon.analysis.temperature_trend import fit, fleet_points
from daemon.fleet import map_view, temperature_view, view
from daemon.hmi.access import secured_app
from daemon.hmi.app import REPORT_CSP, run_id_ok
from daemon.hmi.auth import Auth
from daemon.hmi.limits import HmiLimits, int_param
from daemon.store import pg_maps, pg_temperatures
from daemon.store.journal import StoreError
from daemon.store.pg import PgStore
from daemon.store.url import redact

log = logging.getLogger("rumba.fleet")
READER_KEY = web.AppKey("fleet_reader", object)
STALE_KEY = web.AppKey("stale_after_h", float)
ROOTS_KEY = web.AppKey("report_roots", tuple)
RUNS_SHOWN, DAYS_DEFAULT, DAYS_MAX = 50, 90, 3660


class StoreReader:
    """One connection to the fleet store, opened on first use and again after it broke (the
    page keeps answering 503 while the server is down, and recovers by itself)."""

    def __init__(self, dsn: str) -> None:
        self.dsn = dsn
        self.store: PgStore | None = None
        self.down_since: float | None = None  # the store's outage, said once when it begins

    async def call(self, fn: Callable[[PgStore], Awaitable[Any]], empty: Any = None) -> Any:
        try:
            if self.store is None or self.store.conn.closed:
                self.store = await PgStore.connect(self.dsn, app="rumba-fleet", migrate=False)
            result = await fn(self.store)
        except psycopg.errors.UndefinedTable:
            result = empty  # the store answers; no daemon has created the schema yet
        except (psycopg.OperationalError, StoreError) as e:
            await self.close()
            why = " ".join(str(e).split())
            if self.down_since is None:
                self.down_since = time.monotonic()
                log.error("fleet store %s unreachable: %s; the page answers 503 until it is "
                          "back", redact(self.dsn), why)
            raise web.HTTPServiceUnavailable(
                text=f"fleet store {redact(self.dsn)} unreachable: {why}",
                headers={"Retry-After": "10"}) from None
        if self.down_since is not None:
            log.warning("fleet store %s reachable again after %.0f s", redact(self.dsn),
                        time.monotonic() - self.down_since)
            self.down_since = None
        return result

    async def close(self) -> None:
        if self.store is not None:
            with contextlib.suppress(Exception):
                await self.store.close()
            self.store = None


def _reader(request: web.Request) -> StoreReader:
    return request.app[READER_KEY]  # type: ignore[return-value]


def _html(text: str) -> web.Response:
    return web.Response(text=text, content_type="text/html")


async def fleet_rows(request: web.Request) -> list[dict[str, Any]]:
    fleet = await _reader(request).call(lambda s: s.fleet(), [])
    return view.fleet_rows(fleet, time.time(), request.app[STALE_KEY])


async def index(request: web.Request) -> web.Response:
    return _html(view.fleet_page(await fleet_rows(request), request.app[STALE_KEY]))


async def fleet_json(request: web.Request) -> web.Response:
    return web.json_response({"stale_after_h": request.app[STALE_KEY],
                              "machines": await fleet_rows(request)})


async def machine(request: web.Request) -> web.Response:
    name = request.match_info["machine"]
    if not SAFE_NAME.fullmatch(name):  # daemon.yaml's rule: nothing else is in the store
        raise web.HTTPNotFound(text="no such machine (names are 1-32 of A-Z a-z 0-9 _ . -)")
    days = int_param(request, "days", DAYS_DEFAULT, 1, DAYS_MAX)
    since = time.time() - days * 86400.0

    async def load(s: PgStore) -> tuple:
        return (await s.machine(name), await s.runs(name, RUNS_SHOWN),
                await s.trend(name, since), await pg_maps.listed(s.conn, name, RUNS_SHOWN))

    m, runs, trend, maps = await _reader(request).call(load, (None, [], [], []))
    if m is None and not runs and not maps:
        raise web.HTTPNotFound(text=f"no machine {name!r} in the fleet store")
    page = view.machine_page(name, m, runs, trend, days)
    return _html(page.replace("</main>", map_view.maps_section(maps) + "</main>", 1))


async def machine_maps_json(request: web.Request) -> web.Response:
    """A machine's map results of the linear axes, newest first (``limit``, default 50)."""
    name = request.match_info["machine"]
    if not SAFE_NAME.fullmatch(name):
        raise web.HTTPNotFound(text="no such machine (names are 1-32 of A-Z a-z 0-9 _ . -)")
    limit = int_param(request, "limit", RUNS_SHOWN, 1, 1000)
    maps = await _reader(request).call(lambda s: pg_maps.listed(s.conn, name, limit), [])
    return web.json_response({"machine": name, "maps": map_view.maps_json(maps)})


LINK_NAME = re.compile(r"[A-Z0-9]{1,16}")  # a location error's name, e.g. EX0C


async def _against(request: web.Request) -> dict[str, Any]:
    """The chosen link against the chosen channel over the machine's runs
    (query ``channel``, ``link``, ``days``; the first of each by default), fitted as ``rumba
    history --against-temperature`` fits it."""
    name = request.match_info["machine"]
    if not SAFE_NAME.fullmatch(name):
        raise web.HTTPNotFound(text="no such machine (names are 1-32 of A-Z a-z 0-9 _ . -)")
    days = int_param(request, "days", DAYS_DEFAULT, 1, DAYS_MAX)
    channel, link = request.query.get("channel"), request.query.get("link")
    if channel is not None and not SAFE_NAME.fullmatch(channel):
        raise web.HTTPBadRequest(text="channel: 1-32 of A-Z a-z 0-9 _ . -")
    if link is not None and not LINK_NAME.fullmatch(link):
        raise web.HTTPBadRequest(text="link: a location error's name, e.g. EX0C")
    since = time.time() - days * 86400.0

    async def load(s: PgStore) -> tuple:
        names = await pg_temperatures.channels(s.conn, name)
        ch = channel if channel is not None else (names[0] if names else None)
        rows = (await pg_temperatures.readings(s.conn, name, since, ch)
                if ch in names else [])
        return names, ch, rows

    names, ch, rows = await _reader(request).call(load, ([], None, []))
    if not names:
        raise web.HTTPNotFound(text=f"no temperature readings of machine {name!r} in the "
                                    "fleet store")
    if ch not in names:
        raise web.HTTPNotFound(text=f"machine {name!r} has no readings of channel {ch!r} "
                                    f"(channels: {', '.join(names)})")
    links = temperature_view.links_of(rows)
    lk = link if link is not None else (links[0] if links else "")
    if link is not None and link not in links:
        raise web.HTTPNotFound(text=f"no run of {name!r} in the last {days} days has link "
                                    f"{link} (links: {', '.join(links) or 'none'})")
    pts, unit = fleet_points(rows, lk)
    unit = unit or ("µrad" if lk[1:2] in ("A", "B", "C") else "µm")
    return {"name": name, "channel": ch, "link": lk, "channels": names, "links": links,
            "rows": rows, "points": pts, "fit": fit(pts, unit), "unit": unit, "days": days}


async def against_temperature(request: web.Request) -> web.Response:
    d = await _against(request)
    return _html(temperature_view.page(d["name"], d["channel"], d["link"], d["channels"],
                                       d["links"], d["rows"], d["points"], d["fit"],
                                       d["unit"], d["days"]))


async def against_temperature_json(request: web.Request) -> web.Response:
    d = await _against(request)
    f = d["fit"]
    return web.json_response({
        "machine": d["name"], "channel": d["channel"], "link": d["link"], "unit": d["unit"],
        "n": f.n, "r": f.r, "slope": f.slope, "slope_std": f.slope_std,
        "slope_u95": f.slope_u95, "slope_unit": f.unit, "text": f.text(d["link"], d["channel"]),
        "points": [{"run_id": p.run_id, "temperature_c": p.temperature_c, "value": p.value,
                    "std": p.std} for p in d["points"]]})


def inside(path: Path, roots: Sequence[Path]) -> bool:
    """Whether ``path`` (symlinks resolved) lies in one of ``roots``."""
    real = path.resolve()
    return any(real.is_relative_to(r.resolve()) for r in roots)


async def report(request: web.Request) -> web.StreamResponse:
    run_id = request.match_info["run_id"]
    if not run_id_ok(run_id):
        raise web.HTTPNotFound(text="no such run")
    stored = await _reader(request).call(lambda s: s.report_path(run_id))
    if stored is None:
        raise web.HTTPNotFound(text=f"no report for run {run_id!r} in the fleet store")
    path = Path(stored)
    roots = request.app[ROOTS_KEY]
    if not path.is_absolute() or not inside(path, roots) or not path.is_file():
        where = ", ".join(str(r) for r in roots) or "none given (--reports-dir)"
        raise web.HTTPNotFound(text=f"report of run {run_id} is {stored} on its daemon's host:"
                                    f" not readable inside this page's report directories"
                                    f" ({where})")
    resp = web.FileResponse(path, headers={"Content-Type": "text/html; charset=utf-8"})
    resp.headers["Content-Security-Policy"] = REPORT_CSP
    return resp


async def fleet_css(request: web.Request) -> web.Response:
    text = resources.files("daemon.fleet").joinpath("fleet.css").read_text(encoding="utf-8")
    return web.Response(text=text, content_type="text/css",
                        headers={"Cache-Control": "no-cache"})


def create_fleet_app(dsn: str, token: str, *, stale_after_h: float = 26.0,
                     reports_dirs: Iterable[Path] = (), secure_cookie: bool = False,
                     secret: bytes | None = None, limits: HmiLimits | None = None,
                     bind_host: str | None = None, public_origins: Iterable[str] = ()
                     ) -> web.Application:
    """The fleet page over the store at ``dsn``; the other arguments mean what they mean for
    the HMI (``daemon.hmi.app.create_app``)."""
    app = secured_app(Auth(token, secure_cookie, secret=secret), limits, bind_host,
                      public_origins, "fleet page")
    app[READER_KEY] = StoreReader(dsn)
    app[STALE_KEY] = float(stale_after_h)
    app[ROOTS_KEY] = tuple(Path(d) for d in reports_dirs)

    async def close_store(app: web.Application) -> None:
        await app[READER_KEY].close()  # type: ignore[attr-defined]

    app.on_cleanup.append(close_store)
    app.router.add_get("/", index)
    app.router.add_get("/fleet.css", fleet_css)
    app.router.add_get("/api/fleet", fleet_json)
    app.router.add_get("/machines/{machine:[^/]{1,64}}", machine)
    app.router.add_get("/machines/{machine:[^/]{1,64}}/temperature", against_temperature)
    app.router.add_get("/api/machines/{machine:[^/]{1,64}}/maps", machine_maps_json)
    app.router.add_get("/api/machines/{machine:[^/]{1,64}}/temperature",
                       against_temperature_json)
    app.router.add_get("/reports/{run_id:[A-Za-z0-9_.-]{1,64}}.html", report)
    return app
