"""The operator page's compensation API: the proposal of a machine's last finished run, its
confirmation by the signed-in operator, and the rollback (``daemon.compensation.propose``)."""

from __future__ import annotations

import asyncio
import contextlib
import copy
import dataclasses
import json
import logging
import threading
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from aiohttp import web

from contracts.yaml_files import ConfigError
from daemon.compensation import journal as cj
from daemon.compensation.apply import ApplyError, Written, confirm, rollback
from daemon.compensation.listing import listing_json, row_listing
from daemon.compensation.propose import (
    CompensationRefused,
    ControllerModelError,
    Proposal,
    changed_since,
    propose,
    spec_of,
)
from daemon.hmi.access import page_asset
from daemon.hmi.people import audit, require_journaled, who
from daemon.reports.proposal import proposal_dict, why_nothing
from daemon.run.session import Session
from daemon.store.compensation_rows import compensations_state
from daemon.store.journal import RunRow, Store, StoreError, validate_run_id

FINISHED = ("DONE", "IMPORTED")  # a run that ended with an identification (not aborted)
SCAN_RUNS = 50  # the last finished run is looked for among this many of the machine's runs
LOCK_KEY = web.AppKey("compensation_lock", asyncio.Lock)
log = logging.getLogger("rumba.hmi")


def last_finished(store: Store, machine: str) -> RunRow | None:
    """The machine's most recent finished run, or None."""
    return next((r for r in store.runs(machine, SCAN_RUNS) if r.state in FINISHED), None)


def _row_dict(r: cj.CompensationRow) -> dict[str, Any]:
    return {"id": r.id, "run_id": r.run_id, "state": r.state, "by": r.confirmed_by,
            "reason": r.reason, "created_at": r.created_at, "applied_at": r.applied_at,
            "rollback": r.is_rollback, "values": [v.as_dict() for v in r.values]}


def _why_not(session: Session, store: Store) -> tuple[dict[str, Any], Proposal | None]:
    """The machine's state of compensation and the proposal for its last finished run (None
    with ``why`` saying why there is nothing to propose)."""
    setup = session.setup
    out: dict[str, Any] = {"machine": setup.name, "busy": session.busy, "run": None,
                           "proposal": None, "why": None}
    last = cj.last_applied(store, setup.name)
    out["last_applied"] = _row_dict(last) if last else None
    if last is not None:  # what a rollback writes, address by address, as written
        with contextlib.suppress(ConfigError):
            spec = spec_of(setup)
            if spec is not None:
                now = dataclasses.replace(last, values=tuple(v.reversed() for v in last.values))
                out["last_applied"]["undo"] = listing_json(row_listing(spec, now))
    out["journal"] = [_row_dict(r) for r in cj.rows(store, setup.name)[-5:]][::-1]
    try:
        if spec_of(setup) is None:
            out["why"] = ("no controller_kinematics section in the machine file: nothing rumba "
                          "may write to this controller")
            return out, None
    except ConfigError as e:
        out["why"] = f"refused: {e}"
        return out, None
    run = last_finished(store, setup.name)
    if run is None:
        out["why"] = "no finished run of this machine yet: run a verification first"
        return out, None
    out["run"] = {"id": run.id, "started_at": run.started_at, "ended_at": run.ended_at,
                  "verdict": run.verdict, "state": run.state}
    later = changed_since(store, setup.name, run.started_at)
    if later is not None:
        out["why"] = (f"the controller's model changed after run {run.id} started (journal "
                      f"#{later.id}, {later.state}, by {later.confirmed_by}): run a "
                      "verification first")
        return out, None
    try:
        p = propose(setup, store, run.id)
    except (CompensationRefused, ControllerModelError, ConfigError, StoreError) as e:
        out["why"] = f"refused: {e}"
        return out, None
    out["proposal"] = proposal_dict(p)
    out["why"] = why_nothing(p) or None
    return out, p


def _error(status: int, text: str, **extra: Any) -> web.Response:
    return web.json_response({"error": text, **extra}, status=status)


async def _body(request: web.Request, *fields: str) -> dict[str, Any]:
    """The JSON object of the request with these string fields ("name?": optional), else
    400."""
    try:
        body = json.loads(await request.text())
    except (ValueError, UnicodeDecodeError):
        raise web.HTTPBadRequest(text="send a JSON object") from None
    if not isinstance(body, dict):
        raise web.HTTPBadRequest(text="send a JSON object")
    optional = {f[:-1] for f in fields if f.endswith("?")}
    fields = tuple(f.rstrip("?") for f in fields)
    for f in fields:
        if f in optional and f not in body:
            continue
        if not isinstance(body.get(f), str) or not 0 < len(body[f]) <= 64:
            raise web.HTTPBadRequest(text=f"{f} must be a string of 1 to 64 characters")
    if "again" in body and not isinstance(body["again"], bool):
        raise web.HTTPBadRequest(text="again must be true or false")
    return {f: body[f] for f in fields if f in body} | (
        {"again": body["again"]} if "again" in body else {})


async def script(request: web.Request) -> web.Response:
    """The panel's script (behind the page's sign-in, like the page itself)."""
    return web.Response(text=page_asset("compensation.js"), content_type="application/javascript",
                        headers={"Cache-Control": "no-cache"})


class Views:
    """The compensation view of each machine, computed off the event loop (on the
    loop, a page refreshing a re-identification stalled the run) from the estimate the run
    stored when it ended (``daemon.compensation.identified``; a run journaled before that is
    identified here once and stored), and kept per machine, last finished run and journal
    state: warmed when a run ends (the session's status listener) and served from here until
    the journal changes. One connection of its own, used by one worker thread at a time (the
    lock also makes concurrent requests for the same view wait for one computation instead of
    each doing it)."""

    def __init__(self, journal: Path) -> None:
        self.journal = journal
        self._lock = threading.Lock()
        self._store: Store | None = None
        self._cache: dict[str, tuple[tuple, dict[str, Any], Proposal | None]] = {}

    def _key(self, store: Store, machine: str) -> tuple:
        run = last_finished(store, machine)
        return (run.id if run else None, *compensations_state(store, machine))

    def get(self, session: Session) -> tuple[dict[str, Any], Proposal | None]:
        """The view (a fresh copy; ``busy`` as now) and the proposal; blocking: call it in a
        worker thread."""
        name = session.setup.name
        with self._lock:
            if self._store is None:
                self._store = Store(self.journal)
            key = self._key(self._store, name)
            hit = self._cache.get(name)
            if hit is None or hit[0] != key:
                out, p = _why_not(session, self._store)
                hit = self._cache[name] = (key, out, p)
        out = copy.deepcopy(hit[1])
        out["busy"] = session.busy
        return out, hit[2]

    def close(self) -> None:
        with self._lock:
            if self._store is not None:
                self._store.close()
                self._store = None


def _write_in_thread(journal: Path, fn: Callable[[Store], Written]) -> Written:
    """A confirm or rollback (halcmd on a LinuxCNC takes seconds) on a connection of its own,
    in a worker thread: the event loop keeps serving the run and the page meanwhile."""
    store = Store(journal)
    try:
        return fn(store)
    finally:
        store.close()


# at module level: aiohttp's AppKey looks for its module's frame on the stack, which a call
# from a worker thread or hypothesis' runner does not have (UnboundLocalError in AppKey)
VIEWS_KEY = web.AppKey("compensation_views", Views)


def add_routes(app: web.Application, sessions_key: web.AppKey, store_key: web.AppKey) -> None:
    """GET /api/compensation?machine=, POST /api/compensation/confirm {machine, run_id,
    listing[, again]} (``listing``: the proposal's listing_fingerprint the person reviewed)
    and /api/compensation/rollback {machine} on ``app`` (behind its access layer)."""
    app[LOCK_KEY] = asyncio.Lock()
    views_key = VIEWS_KEY

    def views(request: web.Request) -> Views:
        if views_key not in request.app:
            request.app[views_key] = Views(request.app[store_key].path)
        return request.app[views_key]

    async def warm_on_run_end(app_: web.Application) -> None:
        """Compute each machine's view when its run ends, before anyone asks for it."""
        if views_key not in app_:
            app_[views_key] = Views(app_[store_key].path)
        v: Views = app_[views_key]
        loop = asyncio.get_running_loop()
        for session in app_[sessions_key].values():
            seen: dict[str, str | None] = {"run": session.run_id}

            def on_status(st: dict[str, Any], s: Session = session,
                          seen: dict[str, str | None] = seen) -> None:
                if not st.get("busy") and st.get("run_id") != seen["run"]:
                    seen["run"] = st.get("run_id")
                    task = loop.create_task(asyncio.to_thread(_quiet_get, v, s))
                    _BACKGROUND.add(task)
                    task.add_done_callback(_BACKGROUND.discard)

            session.listeners.append(on_status)

    async def close_views(app_: web.Application) -> None:
        if views_key in app_:
            await asyncio.to_thread(app_[views_key].close)

    app.on_startup.append(warm_on_run_end)
    app.on_cleanup.append(close_views)

    def session_of(request: web.Request, name: str | None, status: int) -> Session:
        sessions: Mapping[str, Session] = request.app[sessions_key]
        if name is None or name not in sessions:
            raise _http(status, f"no machine {name!r}")
        return sessions[name]

    async def get_proposal(request: web.Request) -> web.Response:
        name = request.query.get("machine")
        if name is None or not 0 < len(name) <= 64:
            raise web.HTTPBadRequest(text="machine must be a machine name (1 to 64 characters)")
        session = session_of(request, name, 404)
        out, _ = await asyncio.to_thread(views(request).get, session)
        return web.json_response(out)

    async def post_confirm(request: web.Request) -> web.Response:
        body = await _body(request, "machine", "run_id", "listing?")
        session, store = session_of(request, body["machine"], 422), request.app[store_key]
        require_journaled(request, store, session.setup.name, "engineer", "confirm",
                          "confirming a compensation", body["run_id"])
        if not isinstance(body.get("listing"), str):  # what the person reviewed and confirms
            raise web.HTTPBadRequest(text="listing must be the proposal's listing_fingerprint "
                                          "(GET /api/compensation): what the person reviewed "
                                          "and confirms")
        return audit(request, store, session.setup.name, "confirm",
                     await confirm_body(request, body), body["run_id"])

    async def confirm_body(request: web.Request, body: dict[str, Any]) -> web.Response:
        again = body.pop("again", False) is True
        session = session_of(request, body["machine"], 422)
        try:
            validate_run_id(body["run_id"])
        except StoreError:
            return _error(422, f"{body['run_id']!r} is not a run id")
        journal: Path = request.app[store_key].path
        by = who(request)
        async with request.app[LOCK_KEY]:  # one HMI write at a time
            if session.busy:
                return _error(409, f"{session.setup.name}: a run is active ({session.state}); "
                                   "confirm once it has ended")
            state, p = await asyncio.to_thread(views(request).get, session)
            run = state["run"]
            if run is None or run["id"] != body["run_id"]:
                return _error(409, f"run {body['run_id']} is not the last finished run of "
                                   f"{session.setup.name} (now: {run['id'] if run else 'none'})"
                                   ": reload the proposal", state=state)
            shown = (state.get("proposal") or {}).get("listing_fingerprint")
            if shown is not None and body["listing"] != shown:
                return _error(409, "the values to write are not the ones this page showed "
                                   f"(listing {body['listing']}, now {shown}): reload the "
                                   "proposal and review it again", state=state)
            if p is None or p.refusals or not p.values:
                if p is not None and p.refusals:  # journaled, as `rumba compensate --confirm`
                    row = await asyncio.to_thread(_write_in_thread, journal, lambda st: cj.record(
                        st, session.setup.name, p.run_id, p.spec.family, "refused", p.values,
                        confirmed_by=by, reason=state["why"]))
                    state["why"] += f" (journal #{row})"
                return _error(409, state["why"], state=state)

            def write(st: Store) -> Any:
                try:
                    return confirm(session.setup, st, session.reports_dir, p, by, again=again,
                                   seen=body["listing"])
                except CompensationRefused as e:
                    row = cj.record(st, session.setup.name, p.run_id, p.spec.family,
                                    "refused", p.values, confirmed_by=by, reason=str(e))
                    return (row, str(e), "--again" in str(e))

            try:
                w = await asyncio.to_thread(_write_in_thread, journal, write)
            except ApplyError as e:  # journaled by confirm()
                return _error(502, str(e))
            if isinstance(w, tuple):
                return _error(409, f"refused (journal #{w[0]}): {w[1]}", again=w[2])
        return web.json_response({"state": w.state, "journal": w.row_id, "by": by,
                                  "path": str(w.path) if w.path else None, "note": w.note,
                                  "values": [v.as_dict() for v in p.values],
                                  "writes": listing_json(w.program.listing if w.program
                                                         else [])})

    async def post_rollback(request: web.Request) -> web.Response:
        body = await _body(request, "machine")
        session, store = session_of(request, body["machine"], 422), request.app[store_key]
        require_journaled(request, store, session.setup.name, "engineer", "rollback",
                          "rolling back a compensation")
        return audit(request, store, session.setup.name, "rollback",
                     await rollback_body(request, session))

    async def rollback_body(request: web.Request, session: Session) -> web.Response:
        by = who(request)
        journal: Path = request.app[store_key].path
        async with request.app[LOCK_KEY]:
            if session.busy:
                return _error(409, f"{session.setup.name}: a run is active ({session.state}); "
                                   "roll back once it has ended")
            try:
                w = await asyncio.to_thread(_write_in_thread, journal, lambda st: rollback(
                    session.setup, st, session.reports_dir, by))
            except CompensationRefused as e:
                return _error(409, f"refused: {e}")
            except ApplyError as e:  # journaled by rollback()
                return _error(502, str(e))
        return web.json_response({"state": w.state, "journal": w.row_id, "by": by,
                                  "path": str(w.path) if w.path else None, "note": w.note,
                                  "writes": listing_json(w.program.listing if w.program
                                                         else [])})

    app.router.add_get("/compensation.js", script)
    app.router.add_get("/api/compensation", get_proposal)
    app.router.add_post("/api/compensation/confirm", post_confirm)
    app.router.add_post("/api/compensation/rollback", post_rollback)


_BACKGROUND: set[asyncio.Task] = set()


def _quiet_get(v: Views, session: Session) -> None:
    try:
        v.get(session)
    except Exception:  # a warm-up only: the GET computes (and reports) it again
        log.exception("compensation view of %s", session.setup.name)


def _http(status: int, text: str) -> web.HTTPException:
    return {404: web.HTTPNotFound, 422: web.HTTPUnprocessableEntity}[status](text=text)
