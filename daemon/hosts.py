"""Host names: whether one is a loopback address (the HMI's bind check, local controllers)."""

from __future__ import annotations

import ipaddress


def is_loopback(host: str) -> bool:
    """Whether the HMI host is a loopback address (or ``localhost``)."""
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return host == "localhost"
