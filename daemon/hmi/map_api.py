"""Maps of the linear axes on the operator page: the journaled map results with their figures
(``GET /api/maps[?machine=M&limit=N]``), their report and map file, and the page's script.

A report is looked up by the map's validated id in the journal, never by a path from the
request; ``/maps/ID/map.html`` keeps the report's own relative links (``map.pdf``, ``map.json``)
working. The HTML and the map file are served only while their SHA-256 is the one journaled: a
file changed since is refused (409) rather than shown as the journaled map."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from aiohttp import web

from daemon.hmi.access import page_asset
from daemon.hmi.limits import int_param
from daemon.store import map_results
from daemon.store.journal import StoreError

MAX_MAPS = 500
TYPES = {"map.html": "text/html; charset=utf-8", "map.pdf": "application/pdf",
         "map.json": "application/json"}


def map_dict(m: map_results.MapResult) -> dict[str, Any]:
    """What the page shows of a map: figures, verdict, covered strokes, what is not
    observable, and its files' URLs (the daemon's paths stay on the daemon)."""
    f = m.figures
    base = f"/maps/{m.id}/"
    pdf = bool(m.report_pdf) and Path(m.report_pdf).is_file()
    return {"id": m.id, "kind": m.kind, "machine": m.machine, "run_id": m.run_id,
            "created_at": m.created_at, "verdict": m.verdict, "limit": m.limit_text,
            "volumetric_max_um": m.volumetric_max_um,
            "volumetric_max_u_um": m.volumetric_max_u_um,
            "volumetric_rms_um": m.volumetric_rms_um, "placements": m.placements,
            "covered_mm": f.get("covered_mm", {}),
            "positioning_max_um": f.get("positioning_max_um", {}),
            "unobservable": f.get("unobservable", {}),
            "report": base + "map.html" if m.report_html else None,
            "pdf": base + "map.pdf" if pdf else None, "json": base + "map.json"}


def add_routes(app: web.Application, store_key: web.AppKey, report_csp: str) -> None:
    """The routes; ``report_csp``: the run reports' policy (no script, data: images)."""

    async def maps(request: web.Request) -> web.Response:
        machine = request.query.get("machine")
        if machine is not None and not 0 < len(machine) <= 64:
            raise web.HTTPBadRequest(text="machine must be a machine name (1 to 64 characters)")
        limit = int_param(request, "limit", 20, 1, MAX_MAPS)
        got = map_results.listed(request.app[store_key], machine, limit)
        return web.json_response([map_dict(m) for m in got])

    async def file(request: web.Request) -> web.StreamResponse:
        map_id, name = request.match_info["map_id"], request.match_info["name"]
        try:
            m = map_results.get(request.app[store_key], map_id)
        except StoreError:
            raise web.HTTPNotFound(text="no such map") from None
        path, sha = {"map.html": (m.report_html, m.report_sha256),
                     "map.pdf": (m.report_pdf, ""),
                     "map.json": (m.json_path, m.json_sha256)}[name]
        if not path or not Path(path).is_file():
            raise web.HTTPNotFound(text=f"{name} of map {map_id} is missing")
        if sha and map_results.sha256_of(path) != sha:
            raise web.HTTPConflict(text=f"{name} of map {map_id} changed since it was "
                                        "journaled: not served")
        resp = web.FileResponse(path, headers={"Content-Type": TYPES[name]})
        if name == "map.pdf":
            resp.headers["Content-Disposition"] = f'inline; filename="rumba-{map_id}.pdf"'
        resp.headers["Content-Security-Policy"] = report_csp
        return resp

    async def script(request: web.Request) -> web.Response:
        return web.Response(text=page_asset("maps.js"), content_type="application/javascript",
                            headers={"Cache-Control": "no-cache"})

    app.router.add_get("/api/maps", maps)
    app.router.add_get("/maps/{map_id:[A-Za-z0-9-]{1,64}}/{name:map\\.(?:html|pdf|json)}", file)
    app.router.add_get("/maps.js", script)
