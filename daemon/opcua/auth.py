"""OPC UA user names and passwords of the results server, with the HMI's limit on failed
attempts (daemon/authlimit.py): per client address, the fifth wrong password
locks that address out for 1 s, each further one for twice as long (up to 15 min); all remote
addresses together share a bucket of 20 failures refilled one per 30 s. A locked-out attempt is
refused (BadUserAccessDenied) before its password is compared."""

from __future__ import annotations

import logging
from typing import Any

from asyncua.crypto.permission_rules import User

from contracts.opcua_security import CHANNEL, PasswordUsers
from daemon.authlimit import AuthLimiter, LockoutLimits

log = logging.getLogger("rumba.opcua")


def _remote() -> str | None:
    """The calling client's address (asyncua's peer name of the connection)."""
    peer = getattr(CHANNEL.get(), "name", None)
    return str(peer[0]) if isinstance(peer, tuple) and peer else None


class LimitedPasswordUsers(PasswordUsers):
    def __init__(self, users: dict[str, str] | None,
                 limiter: AuthLimiter | None = None) -> None:
        super().__init__(users)
        self.limiter = limiter or AuthLimiter(LockoutLimits(), name="opcua",
                                              credential="password")

    def get_user(self, iserver: Any, username: str | None = None, password: Any = None,
                 certificate: Any = None) -> User | None:
        if self.users is None:
            return super().get_user(iserver, username, password, certificate)
        remote = _remote()
        wait = self.limiter.retry_after(remote)
        if wait > 0:
            log.warning("opcua: sign-in of %r from %s refused: locked out for %.0f s more",
                        str(username)[:64], remote, wait)
            return None
        user = super().get_user(iserver, username, password, certificate)
        if user is None:
            self.limiter.failed(remote, f"user {str(username)[:64]!r}")
        else:
            self.limiter.succeeded(remote)
        return user
