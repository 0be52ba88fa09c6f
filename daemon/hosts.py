"""Host names: whether one is a loopback address (the HMI's bind check, local controllers), and
Host and Origin values in their one normal form (the HMI's DNS-rebinding check, the
configuration's public origins)."""

from __future__ import annotations

import ipaddress
import re

_DEFAULT_PORT = {"http": 80, "https": 443}
# Host header / origin authority: a DNS name, an IPv4 address or a bracketed IPv6 address, and
# an optional port. Nothing else (no user info "a@b", no path): what is compared is what is seen.
_HOSTPORT = r"(\[[0-9a-f:.]{2,45}\]|[a-z0-9](?:[a-z0-9.-]{0,252}))(?::([0-9]{1,5}))?"
_HOST_RE = re.compile(_HOSTPORT)
_ORIGIN_RE = re.compile(r"(https?)://" + _HOSTPORT)


def is_loopback(host: str) -> bool:
    """Whether the HMI host is a loopback address (or ``localhost``)."""
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return host == "localhost"


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
