"""HMI request limits: timeouts and sizes, the daemon-wide failed-authentication limiter, the
allowed Host / Origin values (the DNS-rebinding defence) and bounded query values."""

from __future__ import annotations

import ipaddress
import logging
import re
import sys
from collections.abc import Iterable, MutableMapping
from dataclasses import dataclass
from typing import Any

from aiohttp import web
from aiohttp.http_exceptions import HttpProcessingError
from aiohttp.web import RequestPayloadError

from daemon.authlimit import AuthLimiter, LockoutLimits, client_key  # noqa: F401
from daemon.hosts import normal_host, normal_origin

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


@dataclass(frozen=True)
class HmiLimits(LockoutLimits):
    """Every bound the HMI server enforces (README "HMI limits"): the failed-sign-in lockout's
    (``LockoutLimits``) and the request's."""

    header_timeout_s: float = 10.0  # whole request line + headers; also the idle keep-alive
    body_timeout_s: float = 10.0    # whole request body, once the headers are in
    linger_s: float = 2.0           # unread body drained after an early answer, then close
    max_body_bytes: int = 64 * 1024
    max_line_bytes: int = 4096      # request line (method, path, query)
    max_field_bytes: int = 8190     # one header line (browsers send every localhost cookie)
    max_headers: int = 64

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
