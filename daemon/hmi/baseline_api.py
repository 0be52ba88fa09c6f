"""The drift baseline on the operator page: show it, and let a person set or confirm one."""

# ``GET /api/machines/NAME/baseline[?run_id=R]``: the baseline, a proposal waiting, the last
# decisions, and (with run_id) why R should not become the baseline
# (``compensation.baseline_check``: it FAILed, predates a compensation, or was identified
# against a model the controller no longer runs) — the page disables its button with that
# reason instead of asking and then refusing. ``POST`` ``{"run_id": …, "by": "Anna Berg",
# "note": …, "override": "reason"}`` (``run_id`` left out: confirm the proposed one)
# journals the decision with the person's name and how they were signed in; a run with
# objections is refused (409, the objections) unless ``override`` gives the reason, which is
# journaled with them. Only an engineer or admin decides; signed in with an account, the
# account's name is the person (a typed "by" is ignored); with the shared token (the token
# login or a script's bearer) the person types their name and the note says so.

from __future__ import annotations

import asyncio
from collections.abc import Mapping
from typing import Any

from aiohttp import web

from daemon.compensation.baseline_check import (
    BaselineRefused,
    check_override,
    objections,
    set_baseline,
)
from daemon.compensation.names import BadName, validate_by
from daemon.hmi.access import page_asset, require
from daemon.hmi.compensation_api import who
from daemon.store import baselines
from daemon.store.journal import RunIdError, Store, StoreError

MAX_BODY = 4096


def add_routes(app: web.Application, sessions_key: web.AppKey, store_key: web.AppKey) -> None:
    lock = asyncio.Lock()

    def machine(request: web.Request) -> str:
        name = request.match_info["machine"]
        if name not in request.app[sessions_key]:
            raise web.HTTPNotFound(text=f"no machine {name!r}")
        return name

    async def get(request: web.Request) -> web.Response:
        name = machine(request)
        out = view(request.app[store_key], name)
        run_id = request.query.get("run_id")
        if run_id is not None:
            try:
                out["objections"] = objections(request.app[store_key], name, run_id)
            except (StoreError, RunIdError) as e:
                return web.json_response({"error": str(e)}, status=404)
            out["run_id"] = run_id
        return web.json_response(out)

    async def post(request: web.Request) -> web.Response:
        name = machine(request)
        if (request.content_length or 0) > MAX_BODY:
            return web.json_response({"error": "body too large"}, status=413)
        try:
            body = await request.json()
        except ValueError:
            return web.json_response({"error": "expected a JSON object"}, status=400)
        if not isinstance(body, dict):
            return web.json_response({"error": "expected a JSON object"}, status=400)
        store: Store = request.app[store_key]
        ident = require(request, "engineer", "setting the drift baseline")
        try:
            person = ident.name if ident.via == "password" else \
                validate_by(body.get("by"), "by", allow_unattended=False)
        except BadName as e:
            return web.json_response({"error": str(e)}, status=422)
        note = body.get("note", "")
        if not isinstance(note, str) or len(note) > 300:
            return web.json_response({"error": "note: text of at most 300 characters"},
                                     status=422)
        override = body.get("override")
        if override is not None:
            try:
                override = check_override(override, "override")
            except BadName as e:
                return web.json_response({"error": str(e)}, status=422)
        async with lock:
            run_id = body.get("run_id")
            if run_id is None:
                wait = baselines.pending(store, name)
                if wait is None:
                    return web.json_response({"error": f"{name}: no proposed baseline to "
                                                       "confirm; give run_id"}, status=409)
                run_id = wait.run_id
            if not isinstance(run_id, str):
                return web.json_response({"error": "run_id: a run id"}, status=422)
            try:
                set_baseline(store, name, run_id, person, (note + " " if note else "")
                             + f"[{ident.role} via {ident.via}, {who(request)}]", override)
            except BaselineRefused as e:
                return web.json_response({"error": str(e), "objections": e.objections},
                                         status=409)
            except (StoreError, RunIdError) as e:
                return web.json_response({"error": str(e)}, status=409)
        return web.json_response(view(store, name))

    app.router.add_get("/baseline.js", script)
    app.router.add_get("/api/machines/{machine}/baseline", get)
    app.router.add_post("/api/machines/{machine}/baseline", post)


async def script(request: web.Request) -> web.Response:
    """The baseline button's script (behind the page's sign-in, like the page itself)."""
    return web.Response(text=page_asset("baseline.js"), content_type="application/javascript",
                        headers={"Cache-Control": "no-cache"})


def view(store: Store, machine: str) -> dict[str, Any]:
    cur, wait = baselines.current(store, machine), baselines.pending(store, machine)
    questionable: list[str] = []
    if cur is not None:  # set before these objections existed, or overridden: said so
        try:
            questionable = objections(store, machine, cur.run_id)
        except StoreError:
            questionable = []
    out: Mapping[str, Any] = {
        "machine": machine, "baseline": cur.as_dict() if cur else None,
        "proposed": wait.as_dict() if wait else None,
        "text": f"drift judged against {cur.describe()}" if cur else
        "drift not checked: no baseline",
        "history": [b.as_dict() for b in baselines.history(store, machine, 10)],
        "questionable": questionable}
    return dict(out)
