"""HMI request limits: timeouts and sizes, the daemon-wide failed-authentication limiter, the
allowed Host / Origin values (the DNS-rebinding defence) and bounded query values."""

from __future__ import annotations

import ipaddress
import logging
import re
import sys
import time
from collections.abc import Callable, Iterable, MutableMapping
from dataclasses import dataclass
from typing import Any

from aiohttp import web
from aiohttp.http_exceptions import HttpProcessingError
from aiohttp.web import RequestPayloadError

log = logging.getLogger("rumba.hmi")


class ServerLog(logging.LoggerAdapter):
    """aiohttp's server logger, minus the traceback it logs at ERROR for every malformed
    request (bad request line, header, chunk, a body cut short …): anyone who can connect
    sends those, so they are one DEBUG line here. Handler failures (500) keep their
    traceback."""

    def __init__(self) -> None:
        super().__init__(logging.getLogger("rumba.hmi.server"), {})

    def process(self, msg: Any, kwargs: MutableMapping[str, Any]) -> tuple[Any, Any]:
        return msg, kwargs

    def exception(self, msg: Any, *args: Any, exc_info: Any = True, **kw: Any) -> None:
        exc = exc_info if isinstance(exc_info, BaseException) else sys.exc_info()[1]
        if isinstance(exc, RequestPayloadError) or (
                isinstance(exc, HttpProcessingError) and 400 <= (exc.code or 0) < 500):
            first = str(exc).strip().splitlines()
            self.debug("%s: %s", msg % args if args else msg, first[0] if first else exc)
            return
        super().exception(msg, *args, exc_info=exc_info, **kw)


_DEFAULT_PORT = {"http": 80, "https": 443}
# Host header / origin authority: a DNS name, an IPv4 address or a bracketed IPv6 address, and
# an optional port. Nothing else (no user info "a@b", no path): what is compared is what is seen.
_HOSTPORT = r"(\[[0-9a-f:.]{2,45}\]|[a-z0-9](?:[a-z0-9.-]{0,252}))(?::([0-9]{1,5}))?"
_HOST_RE = re.compile(_HOSTPORT)
_ORIGIN_RE = re.compile(r"(https?)://" + _HOSTPORT)


@dataclass(frozen=True)
class HmiLimits:
    """Every bound the HMI server enforces (README "HMI limits")."""

    header_timeout_s: float = 10.0  # whole request line + headers; also the idle keep-alive
    body_timeout_s: float = 10.0    # whole request body, once the headers are in
    linger_s: float = 2.0           # unread body drained after an early answer, then close
    max_body_bytes: int = 64 * 1024
    max_line_bytes: int = 4096      # request line (method, path, query)
    max_field_bytes: int = 8190     # one header line (browsers send every localhost cookie)
    max_headers: int = 64
    free_failures: int = 5          # wrong tokens per client; the 5th locks it out
    lockout_base_s: float = 1.0     # first lockout; doubles at each further failure
    lockout_max_s: float = 900.0
    forget_s: float = 3600.0        # a client's failures are forgotten after this quiet time
    global_burst: int = 20          # failures of all non-loopback clients together …
    global_refill_s: float = 30.0   # … then one more every this many seconds
    max_clients: int = 4096         # clients remembered (memory bound)

    def server_args(self) -> dict[str, Any]:
        """aiohttp ``RequestHandler`` options (``web.Application(handler_args=…)``). aiohttp
        arms its keep-alive timer when the connection opens and again after each answer, and
        closes the connection if no complete request head arrived by then: with a short
        keep-alive this is the header-read timeout (a byte-per-second sender does not reset
        it)."""
        # auto_decompress off: no page sends compressed bodies, and a bad or huge gzip body
        # would be inflated before anything is checked (415 in the middleware instead).
        return {"keepalive_timeout": self.header_timeout_s, "lingering_time": self.linger_s,
                "auto_decompress": False,
                "max_line_size": self.max_line_bytes, "max_field_size": self.max_field_bytes,
                "max_headers": self.max_headers, "logger": ServerLog()}


def client_key(remote: str | None) -> str:
    """Who is limited: an IPv4 address, an IPv6 /64 (one host has billions of addresses), and
    all of loopback as one client (127.0.0.0/8 is a whole /8 for a local attacker)."""
    try:
        ip = ipaddress.ip_address((remote or "").split("%")[0])
    except ValueError:
        return "local"  # unix socket or unknown: one client
    if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
        ip = ip.ipv4_mapped
    if ip.is_loopback:
        return "loopback"
    if isinstance(ip, ipaddress.IPv6Address):
        return str(ipaddress.ip_network(f"{ip}/64", strict=False))
    return str(ip)


@dataclass
class _Client:
    failures: int = 0
    locked_until: float = 0.0
    last: float = 0.0


class AuthLimiter:
    """Failed token attempts, counted for the whole daemon (not per connection or request): a
    client's ``free_failures``-th wrong token locks it out for ``lockout_base_s``, each further
    one for twice as long as the previous one (up to ``lockout_max_s``); all non-loopback
    clients together also share a token bucket, so many addresses cannot add up to a fast
    guesser. A locked-out
    request is answered 429 before its token is looked at. Loopback is exempt from the shared
    bucket (only its own lockout applies) so a remote attacker cannot lock out the machine's
    own operator and scripts. Check and record run without an await in between, so parallel
    requests see each other's failures."""

    def __init__(self, limits: HmiLimits, clock: Callable[[], float] = time.monotonic) -> None:
        self.limits = limits
        self.clock = clock
        self._clients: dict[str, _Client] = {}
        self._tokens = float(limits.global_burst)
        self._refilled = clock()

    def _refill(self, now: float) -> None:
        lim = self.limits
        self._tokens = min(float(lim.global_burst),
                           self._tokens + (now - self._refilled) / lim.global_refill_s)
        self._refilled = now

    def retry_after(self, remote: str | None) -> float:
        """Seconds before ``remote`` may try a token again; 0 = now."""
        now = self.clock()
        key = client_key(remote)
        c = self._clients.get(key)
        wait = max(0.0, c.locked_until - now) if c else 0.0
        if key != "loopback":
            self._refill(now)
            if self._tokens < 1.0:
                wait = max(wait, (1.0 - self._tokens) * self.limits.global_refill_s)
        return wait

    def failed(self, remote: str | None, what: str) -> None:
        """Record a wrong token from ``remote`` (``what``: bearer, login) and log it."""
        lim, now, key = self.limits, self.clock(), client_key(remote)
        c = self._clients.get(key)
        if c is None or (now - c.last > lim.forget_s and now >= c.locked_until):
            c = self._clients[key] = _Client()
            self._prune(now)
        c.failures += 1
        c.last = now
        if key != "loopback":
            self._refill(now)
            self._tokens = max(0.0, self._tokens - 1.0)
        over = c.failures - lim.free_failures + 1
        if over > 0:
            lock = min(lim.lockout_max_s, lim.lockout_base_s * 2.0 ** min(over - 1, 40))
            c.locked_until = now + lock
            log.warning("hmi: wrong token (%s) from %s, %d failures: locked out for %.0f s",
                        what, key, c.failures, lock)
        else:
            log.warning("hmi: wrong token (%s) from %s, %d failures", what, key, c.failures)

    def succeeded(self, remote: str | None) -> None:
        """The right token: the client's own count restarts (the shared bucket does not)."""
        self._clients.pop(client_key(remote), None)

    def _prune(self, now: float) -> None:
        if len(self._clients) <= self.limits.max_clients:
            return
        for k, c in list(self._clients.items()):
            if now - c.last > self.limits.forget_s and now >= c.locked_until:
                del self._clients[k]
        # Still too many (an address sweep): forget the oldest; the shared bucket still holds.
        for k in sorted(self._clients, key=lambda k: self._clients[k].last)[
                :len(self._clients) - self.limits.max_clients]:
            del self._clients[k]


def normal_host(value: str, scheme: str) -> str | None:
    """``host:port`` (lower case, explicit port) of a Host header value, None if malformed."""
    m = _HOST_RE.fullmatch(value.lower())
    if m is None:
        return None
    return f"{m[1]}:{int(m[2]) if m[2] else _DEFAULT_PORT[scheme]}"


def normal_origin(value: str) -> str | None:
    """``scheme://host:port`` of an Origin value, None if malformed (also "null")."""
    m = _ORIGIN_RE.fullmatch(value.lower())
    if m is None:
        return None
    return f"{m[1]}://{m[2]}:{int(m[3]) if m[3] else _DEFAULT_PORT[m[1]]}"


def _bracket(host: str) -> str:
    return f"[{host}]" if ":" in host and not host.startswith("[") else host


class Origins:
    """The Host and Origin values the HMI answers: the address and port the client connected
    to (and ``localhost``, 127.0.0.1, [::1], 0.0.0.0, [::] when that is loopback), the
    configured bind host, and the configured public origins (a DNS name in front of the
    HMI). Any other name is a DNS-rebinding page or a misconfiguration: 421."""

    def __init__(self, bind_host: str | None = None, public: Iterable[str] = ()) -> None:
        self.names: set[str] = set()
        if bind_host:
            self.names.add(_bracket(bind_host.lower()))
        self.origins: set[str] = set()
        for o in public:
            n = normal_origin(o.rstrip("/"))
            if n is None:
                raise ValueError(f"public origin {o!r} is not scheme://host[:port]")
            self.origins.add(n)

    def hosts(self, local: tuple[str, int], scheme: str) -> set[str]:
        """Allowed normalised Host values for a connection to ``local`` (address, port)."""
        addr, port = local[0].split("%")[0].lower(), local[1]
        names = set(self.names) | {_bracket(addr)}
        try:
            ip = ipaddress.ip_address(addr)
            if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
                ip = ip.ipv4_mapped  # a dual-stack socket bound to [::]
                names.add(str(ip))
            if ip.is_loopback:
                # A connection to 0.0.0.0 / [::] ends on loopback too (rumba verify --daemon
                # uses hmi.host as it is); no DNS name can make a browser send these.
                names |= {"localhost", "127.0.0.1", "[::1]", "0.0.0.0", "[::]"}
        except ValueError:
            pass
        hosts = {f"{n}:{port}" for n in names}
        hosts |= {o.split("://", 1)[1] for o in self.origins if o.startswith(scheme + "://")}
        return hosts

    def host_ok(self, host: str | None, local: tuple[str, int], scheme: str) -> bool:
        n = normal_host(host, scheme) if host else None
        return n is not None and n in self.hosts(local, scheme)

    def origin_ok(self, origin: str, local: tuple[str, int], scheme: str) -> bool:
        n = normal_origin(origin)
        return n is not None and (n in self.origins or n in {
            f"{scheme}://{h}" for h in self.hosts(local, scheme)})


_INT = re.compile(r"[0-9]{1,9}")


def int_param(request: web.Request, name: str, default: int, lo: int, hi: int) -> int:
    """Query parameter ``name`` as an integer in [lo, hi]; 400 naming the bounds otherwise."""
    raw = request.query.get(name)
    if raw is None:
        return default
    if not _INT.fullmatch(raw) or not lo <= int(raw) <= hi:
        raise web.HTTPBadRequest(text=f"{name} must be an integer from {lo} to {hi}")
    return int(raw)
