"""Who acts on the HMI: the name a confirmation is journaled under, and the audit
trail of what people ask for (``daemon.store.actions``) — refusals for a role too low included."""

from __future__ import annotations

import json

from aiohttp import web

from daemon.compensation.names import BadName, validate_by
from daemon.hmi.access import COOKIE, IDENTITY_KEY, VIA_KEY, require
from daemon.store.actions import record_action
from daemon.store.journal import Store


def who(request: web.Request) -> str:
    """Who confirms, as the access layer knows the client (never a name the client sends):
    the person's account name when signed in with a password,
    ``hmi:<session id prefix>@<address>`` for a page signed in with the token,
    ``hmi:token@<address>`` for a script with the bearer token."""
    ident = request.get(IDENTITY_KEY)
    if ident is not None and ident.via == "password":
        name = ident.name
    elif request.get(VIA_KEY) == "cookie":
        sid = (request.cookies.get(COOKIE) or "").split(".")[0]
        name = f"hmi:{sid[:8]}@{request.remote}"
    else:
        name = f"hmi:token@{request.remote}"
    try:  # the same rules as --by: it is printed in the journal and the reports
        return validate_by(name, "HMI session", allow_unattended=False)
    except BadName as e:
        raise web.HTTPBadRequest(text=str(e)) from None


def journal(request: web.Request, store: Store, machine: str, action: str, outcome: str,
            run_id: str = "") -> None:
    """One action of the request's person in the audit trail."""
    ident = request.get(IDENTITY_KEY)
    record_action(store, machine, action, ident.name if ident else "token",
                  ident.role if ident else "admin", ident.via if ident else "bearer",
                  outcome[:500], run_id=run_id)


def audit(request: web.Request, store: Store, machine: str, action: str,
          resp: web.Response, run_id: str = "") -> web.Response:
    """The person's confirm / rollback and its outcome (the answer's error) in the trail."""
    outcome = "ok" if resp.status < 300 else \
        f"refused: {json.loads(resp.text or '{}').get('error', resp.status)}"
    journal(request, store, machine, action, outcome, run_id)
    return resp


def require_journaled(request: web.Request, store: Store, machine: str, role: str,
                      action: str, what: str, run_id: str = "") -> None:
    """``access.require``; a refusal (a role too low) is journaled before the 403."""
    try:
        require(request, role, what)
    except web.HTTPForbidden as e:
        journal(request, store, machine, action, f"refused: {e.text}", run_id)
        raise
