"""HMI authentication: the operator token and signed session cookies that survive a daemon
restart.

A session cookie is ``<id>.<expiry>.<user>.<generation>.<signature>``: HMAC-SHA256 over the
rest with a key
derived from a random secret (a 0600 file in the daemon's state directory, created on first
start) and the operator token, so changing the token signs everybody out. The CSRF token is
derived from the session id with the same key (nothing to store). Logout revokes the id; the
revocations are journaled in the store until the cookie would have expired anyway.

With accounts (``hmi.users_file``, ``daemon.hmi.users``) a session belongs to a person: its
role is looked up in the users file on every request, and the cookie carries a fingerprint of
the password hash, so a new password or a removed account ends that person's sessions. Without
accounts the form takes the token and the session acts as ``token`` with the admin role.
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
from dataclasses import dataclass
from pathlib import Path

from contracts.input_files import read_bounded
from daemon.hmi.users import RANK, Accounts, User
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


TOKEN_NAME = "token"  # who acts with the token (scripts; the form when there are no accounts)


@dataclass(frozen=True)
class Identity:
    """Who sends a request: the account's name and role, and how they signed in
    (``password``, ``token-login``: the form with the token, ``bearer``: a script)."""

    name: str
    role: str
    via: str
    csrf: str = ""

    def may(self, role: str) -> bool:
        return RANK[self.role] >= RANK[role]


class Auth:
    """Token check and signed, revocable cookie sessions (of accounts when there are any)."""

    def __init__(self, token: str, secure_cookie: bool = False, *, secret: bytes | None = None,
                 store: Store | None = None, ttl_s: float = SESSION_TTL_S,
                 accounts: Accounts | None = None) -> None:
        self.accounts = accounts
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

    def new_session(self, now: float | None = None, user: User | None = None
                    ) -> tuple[str, str]:
        """(cookie value, CSRF token) of a new session starting at ``now`` (of ``user``, or
        of the token when None)."""
        sid = secrets.token_urlsafe(18)
        who = f"{user.name}.{user.generation}" if user else "."
        payload = f"{sid}.{int((time.time() if now is None else now) + self.ttl_s)}.{who}"
        return f"{payload}.{self._sign(payload)}", self.csrf(sid)

    def _verify(self, cookie: str | None) -> tuple[str, float, str, str] | None:
        """(session id, expiry, user, generation) of a well-signed, unexpired, unrevoked
        cookie, else None."""
        parts = (cookie or "").split(".")
        if len(parts) != 5 or not parts[1].isdigit() or len(parts[1]) > 12:
            return None
        sid, exp, user, gen, sig = parts
        if not hmac.compare_digest(sig.encode(), self._sign(".".join(parts[:4])).encode()):
            return None
        if int(exp) < time.time() or sid in self.revoked:
            return None
        return sid, float(exp), user, gen

    def identity(self, cookie: str | None) -> Identity | None:
        """Who a live session belongs to (the role as the users file says now), or None."""
        v = self._verify(cookie)
        if v is None:
            return None
        sid, _, name, gen = v
        if not name:  # a token session: only while there are no accounts
            return None if self.accounts else Identity(TOKEN_NAME, "admin", "token-login",
                                                       self.csrf(sid))
        user = self.accounts.get(name) if self.accounts else None
        if user is None or not hmac.compare_digest(gen.encode(), user.generation.encode()):
            return None  # removed, or a new password since this session began
        return Identity(user.name, user.role, "password", self.csrf(sid))

    def session(self, cookie: str | None) -> str | None:
        """The CSRF token of a live session, or None."""
        i = self.identity(cookie)
        return None if i is None else i.csrf

    def revoke(self, cookie: str | None) -> bool:
        """Sign a session out for good (also across restarts); False if it was not live."""
        v = self._verify(cookie)
        if v is None:
            return False
        now = time.time()
        self.revoked = {s: e for s, e in self.revoked.items() if e >= now}
        self.revoked[v[0]] = v[1]
        if self.store is not None:
            self.store.revoke_hmi_session(v[0], v[1])
        return True
