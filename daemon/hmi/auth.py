"""HMI authentication: the operator token and signed session cookies that survive a daemon
restart.

A session cookie is ``<id>.<expiry>.<signature>``: HMAC-SHA256 over id and expiry with a key
derived from a random secret (a 0600 file in the daemon's state directory, created on first
start) and the operator token, so changing the token signs everybody out. The CSRF token is
derived from the session id with the same key (nothing to store). Logout revokes the id; the
revocations are journaled in the store until the cookie would have expired anyway.
"""

from __future__ import annotations

import base64
import contextlib
import hashlib
import hmac
import os
import secrets
import stat
import tempfile
import time
from pathlib import Path

from contracts.input_files import read_bounded
from daemon.store.journal import Store

SESSION_TTL_S = 12 * 3600
SECRET_FILE = "hmi-session.key"
_SECRET_BYTES = 32


class SecretError(Exception):
    """The session secret file cannot be used; one line naming the file."""


def load_or_create_secret(path: Path) -> bytes:
    """The session signing secret in ``path``; created (mode 0600, atomically) when absent."""
    try:
        st = path.stat()
    except FileNotFoundError:
        return _create_secret(path)
    except OSError as e:
        raise SecretError(f"{path}: cannot read the HMI session secret: {e.strerror}") from None
    mode = stat.S_IMODE(st.st_mode)
    if mode & 0o077:
        raise SecretError(f"{path}: HMI session secret is readable by others (mode {mode:04o});"
                          " chmod 600 it")
    try:  # a regular file of at most 4 KiB: a FIFO would block the start
        secret = bytes.fromhex(read_bounded(path, SecretError, 4096, "session secret").decode(
            "ascii").strip())
    except OSError as e:
        raise SecretError(f"{path}: cannot read the HMI session secret: {e.strerror}") from None
    except (ValueError, UnicodeDecodeError):
        secret = b""
    if len(secret) < _SECRET_BYTES:
        raise SecretError(f"{path}: not a rumba HMI session secret ({_SECRET_BYTES} bytes hex); "
                          "delete it and a new one is made at the next start (signs everyone out)")
    return secret


def _create_secret(path: Path) -> bytes:
    secret = secrets.token_bytes(_SECRET_BYTES)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        # mkstemp creates the file 0600; link() publishes it whole or not at all, and fails if
        # another process made one meanwhile (then that one is used).
        fd, tmp = tempfile.mkstemp(prefix=".hmi-secret-", dir=path.parent)
        try:
            os.write(fd, secret.hex().encode() + b"\n")
            os.fsync(fd)
            os.close(fd)
            try:
                os.link(tmp, path)
            except FileExistsError:
                return load_or_create_secret(path)
        finally:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
    except OSError as e:
        raise SecretError(f"{path}: cannot create the HMI session secret: {e.strerror}") from None
    return secret


def _b64(data: bytes) -> str:
    return base64.urlsafe_b64encode(data).rstrip(b"=").decode()


class Auth:
    """Token check and signed, revocable cookie sessions."""

    def __init__(self, token: str, secure_cookie: bool = False, *, secret: bytes | None = None,
                 store: Store | None = None, ttl_s: float = SESSION_TTL_S) -> None:
        self.token = token.encode()
        self.secure_cookie = secure_cookie
        self.ttl_s = ttl_s
        self.store = store
        # No secret (tests, no state directory): sessions last as long as this object.
        secret = secrets.token_bytes(_SECRET_BYTES) if secret is None else secret
        self._key = hmac.new(secret, b"rumba-hmi-session\0" + self.token, hashlib.sha256).digest()
        self.revoked: dict[str, float] = store.revoked_hmi_sessions() if store else {}

    def token_ok(self, candidate: str) -> bool:
        return hmac.compare_digest(candidate.encode(), self.token)

    def _sign(self, payload: str) -> str:
        return _b64(hmac.new(self._key, payload.encode(), hashlib.sha256).digest())

    def csrf(self, sid: str) -> str:
        return self._sign("csrf\0" + sid)[:32]

    def new_session(self, now: float | None = None) -> tuple[str, str]:
        """(cookie value, CSRF token) of a new session starting at ``now``."""
        sid = secrets.token_urlsafe(18)
        payload = f"{sid}.{int((time.time() if now is None else now) + self.ttl_s)}"
        return f"{payload}.{self._sign(payload)}", self.csrf(sid)

    def _verify(self, cookie: str | None) -> tuple[str, float] | None:
        """(session id, expiry) of a well-signed, unexpired, unrevoked cookie, else None."""
        parts = (cookie or "").split(".")
        if len(parts) != 3 or not parts[1].isdigit() or len(parts[1]) > 12:
            return None
        sid, exp, sig = parts
        if not hmac.compare_digest(sig.encode(), self._sign(f"{sid}.{exp}").encode()):
            return None
        if int(exp) < time.time() or sid in self.revoked:
            return None
        return sid, float(exp)

    def session(self, cookie: str | None) -> str | None:
        """The CSRF token of a live session, or None."""
        v = self._verify(cookie)
        return None if v is None else self.csrf(v[0])

    def revoke(self, cookie: str | None) -> bool:
        """Sign a session out for good (also across restarts); False if it was not live."""
        v = self._verify(cookie)
        if v is None:
            return False
        now = time.time()
        self.revoked = {s: e for s, e in self.revoked.items() if e >= now}
        self.revoked[v[0]] = v[1]
        if self.store is not None:
            self.store.revoke_hmi_session(*v)
        return True
