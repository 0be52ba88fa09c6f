"""The limit on failed sign-in attempts shared by the HMI (tokens, passwords) and the OPC UA
results server (passwords): per client address, then all remote addresses together."""

from __future__ import annotations

import ipaddress
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

log = logging.getLogger("rumba.hmi")


@dataclass(frozen=True)
class LockoutLimits:
    """The limiter's bounds (README "HMI limits"; the HMI's ``HmiLimits`` extends them)."""

    free_failures: int = 5          # wrong tokens per client; the 5th locks it out
    lockout_base_s: float = 1.0     # first lockout; doubles at each further failure
    lockout_max_s: float = 900.0
    forget_s: float = 3600.0        # a client's failures are forgotten after this quiet time
    global_burst: int = 20          # failures of all non-loopback clients together …
    global_refill_s: float = 30.0   # … then one more every this many seconds
    max_clients: int = 4096         # clients remembered (memory bound)


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

    def __init__(self, limits: LockoutLimits, clock: Callable[[], float] = time.monotonic,
                 name: str = "hmi", credential: str = "token") -> None:
        self.limits = limits
        self.clock = clock
        self.name, self.credential = name, credential  # how its log lines say who and what
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
            log.warning("%s: wrong %s (%s) from %s, %d failures: locked out for %.0f s",
                        self.name, self.credential, what, key, c.failures, lock)
        else:
            log.warning("%s: wrong %s (%s) from %s, %d failures", self.name, self.credential,
                        what, key, c.failures)

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
