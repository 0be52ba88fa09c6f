"""Who may use the web pages (HMI and fleet): Host / Origin, token or session cookie, login.

Auth: ``Authorization: Bearer <token>`` (scripts) or a login form that sets an HttpOnly,
SameSite=Strict (and, over TLS, Secure) signed session cookie that survives a daemon restart
(``daemon.hmi.auth``); tokens are compared in constant time. Cookie-authenticated POSTs also
need the per-session CSRF token (header ``X-CSRF-Token``) and an allowed ``Origin``. With
accounts (``hmi.users_file``) the form asks for name and password and every request knows the
person and role (``IDENTITY_KEY``; ``require`` refuses a role too low); the token is then for
scripts only. Every
request needs an allowed ``Host`` (DNS rebinding); wrong tokens are limited daemon-wide, and
headers, bodies and query values are bounded (``daemon.hmi.limits``).
"""

from __future__ import annotations

import asyncio
import hmac
import re
from collections.abc import Awaitable, Callable, Iterable
from html import escape
from importlib import resources
from urllib.parse import parse_qsl

from aiohttp import web

from daemon.hmi.auth import SESSION_TTL_S, TOKEN_NAME, Auth, Identity
from daemon.hmi.limits import AuthLimiter, HmiLimits, Origins

COOKIE = "rumba_session"
CSP = ("default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' data:; "
       "connect-src 'self'; form-action 'self'; frame-ancestors 'none'; base-uri 'none'")
PUBLIC = {"/login", "/hmi.css"}
HMI_NAME = "operator page"  # the HMI's name on the login form (login.html {{page}})

AUTH_KEY = web.AppKey("auth", object)
LIMITS_KEY = web.AppKey("limits", HmiLimits)
LIMITER_KEY = web.AppKey("limiter", AuthLimiter)
ORIGINS_KEY = web.AppKey("origins", Origins)
LOGIN_NAME_KEY = web.AppKey("login_name", str)  # the page the login form signs in to
VIA_KEY = web.RequestKey("via", str)
CSRF_KEY = web.RequestKey("csrf", str)
IDENTITY_KEY = web.RequestKey("identity", Identity)


def page_asset(name: str) -> str:
    """The text of one of the page's files (``daemon.hmi`` package data)."""
    return resources.files("daemon.hmi").joinpath(name).read_text(encoding="utf-8")


async def asset(request: web.Request) -> web.Response:
    name = request.match_info["name"]
    types = {"hmi.js": "application/javascript", "hmi.css": "text/css"}
    return web.Response(text=page_asset(name), content_type=types[name],
                        headers={"Cache-Control": "no-cache"})


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
        request[IDENTITY_KEY] = Identity(TOKEN_NAME, "admin", "bearer")
        return
    # A cookie is signed with a 256-bit key: a wrong one is not a token guess (and expired
    # ones come from honest browsers), so it is not counted and works during a lockout.
    ident = auth.identity(request.cookies.get(COOKIE))
    if ident is not None:
        csrf = ident.csrf
        request[VIA_KEY] = "cookie"
        request[CSRF_KEY] = csrf
        request[IDENTITY_KEY] = ident
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


_TOKEN_FIELDS = ('<label for="token">Access token</label>\n  <input id="token" name="token" '
                 'type="password" autocomplete="current-password" autofocus required>')
_USER_FIELDS = ('<label for="user">Name</label>\n  <input id="user" name="user" '
                'autocomplete="username" autocapitalize="none" autofocus required>\n  '
                '<label for="password">Password</label>\n  <input id="password" '
                'name="password" type="password" autocomplete="current-password" required>')


def require(request: web.Request, role: str, what: str) -> Identity:
    """The request's person when their role is at least ``role``, else 403 naming both."""
    ident = request.get(IDENTITY_KEY)
    if ident is None or not ident.may(role):
        who = f"{ident.name} ({ident.role})" if ident else "nobody"
        need = "an engineer or admin" if role == "engineer" else f"at least {role}"
        raise web.HTTPForbidden(text=f"signed in as {who}: {what} needs {need}")
    return ident


TOKEN_IN_FORM = ('<p class="error">That is the daemon\'s token: it is for scripts, which send '
                 'it in the header <code>Authorization: Bearer &lt;token&gt;</code>. People '
                 'sign in here with their own name and password (<code>rumba users</code> '
                 'makes accounts).</p>')
"""The answer to the token typed into the name and password form."""


def _login_html(request: web.Request, error: str) -> str:
    """The login form naming the page it signs in to (escaped); ``error`` is our own markup.
    One pass over login.html's placeholders, so a value is never itself substituted."""
    auth: Auth = request.app[AUTH_KEY]  # type: ignore[assignment]
    values = {"error": error, "page": escape(request.app[LOGIN_NAME_KEY]),
              "fields": _USER_FIELDS if auth.accounts else _TOKEN_FIELDS}
    return re.sub(r"\{\{(error|page|fields)\}\}", lambda m: values[m.group(1)],
                  page_asset("login.html"))


async def login_page(request: web.Request) -> web.Response:
    return web.Response(text=_login_html(request, ""), content_type="text/html")


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
    user = None
    if auth.accounts is not None:  # a person: name and password (scrypt, in a worker thread)
        user = await asyncio.to_thread(auth.accounts.check, form.get("user", "")[:64],
                                       form.get("password", "")[:1024])
        ok, wrong = user is not None, "Wrong name or password."
        if not ok and any(auth.token_ok(form.get(k, "")[:1024])
                          for k in ("password", "user", "token")):
            # The daemon's token typed into the form: right, but for another door. Not
            # counted as a failure (it is no guess), and not echoed.
            return web.Response(status=401, content_type="text/html", text=_login_html(
                request, TOKEN_IN_FORM))
    else:
        ok, wrong = auth.token_ok(form.get("token", "")), "Wrong token."
    if not ok:
        limiter.failed(request.remote, "login")
        return web.Response(status=401, content_type="text/html", text=_login_html(
            request, f'<p class="error">{wrong}</p>'))
    limiter.succeeded(request.remote)
    cookie, _ = auth.new_session(user=user)
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


def secured_app(auth: Auth, limits: HmiLimits | None, bind_host: str | None,
                public_origins: Iterable[str], login_name: str) -> web.Application:
    """An app behind this page's security (``security``: Host / Origin, token or session
    cookie, bounded requests) with its /login, /logout and the stylesheet; the HMI and the
    fleet page."""
    limits = limits or HmiLimits()
    app = web.Application(middlewares=[security], client_max_size=limits.max_body_bytes,
                          handler_args=limits.server_args())
    app[AUTH_KEY] = auth
    app[LIMITS_KEY] = limits
    app[LIMITER_KEY] = AuthLimiter(limits)
    app[ORIGINS_KEY] = Origins(bind_host, public_origins)
    app[LOGIN_NAME_KEY] = login_name
    app.router.add_get("/login", login_page)
    app.router.add_post("/login", login)
    app.router.add_post("/logout", logout)
    app.router.add_get("/{name:hmi\\.css}", asset)  # public: the login page's stylesheet
    return app
