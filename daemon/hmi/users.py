"""HMI user accounts: a text file the admin edits (or ``rumba users`` writes), one account a
line ``name:role:scrypt$N$r$p$salt$hash``, passwords hashed with the standard library's scrypt.

Roles: ``operator`` starts and aborts runs; ``engineer`` also confirms and rolls back a
compensation; ``admin`` may do everything an engineer may (accounts are managed on the daemon's
PC with ``rumba users``, not from the page). The file is read again when it changes, so an
account added, removed or given a new password takes effect without a restart (a new password
or a removed account signs that person's sessions out).
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import os
import re
import secrets
import stat
import tempfile
from dataclasses import dataclass
from pathlib import Path

ROLES = ("operator", "engineer", "admin")
RANK = {r: i for i, r in enumerate(ROLES)}
NAME_RE = re.compile(r"[a-z][a-z0-9_-]{0,31}")
RESERVED = {"token", "unattended", "hmi", "cli", "cnc", "can", "rerun"}
MIN_PASSWORD = 10
MAX_PASSWORD = 1024
MAX_FILE_BYTES = 1 << 20
# scrypt cost: N=2^14, r=8, p=1 — 16 MiB and ~50 ms a check, the interactive-login setting of
# the scrypt paper; written into each line so a later rumba can raise it
SCRYPT_N, SCRYPT_R, SCRYPT_P = 1 << 14, 8, 1


class UsersError(Exception):
    """The users file or an account cannot be used; one line naming the file (and line)."""


@dataclass(frozen=True)
class User:
    name: str
    role: str
    hash: str  # scrypt$N$r$p$salt$key (base64 without padding)

    @property
    def generation(self) -> str:
        """A short fingerprint of the password hash: a cookie made before a password change
        carries the old one and is refused."""
        return hashlib.sha256(self.hash.encode()).hexdigest()[:10]

    def may(self, role: str) -> bool:
        """Whether this account has at least ``role``."""
        return RANK[self.role] >= RANK[role]


def _b64(b: bytes) -> str:
    return base64.b64encode(b).decode().rstrip("=")


def _unb64(s: str) -> bytes:
    return base64.b64decode(s + "=" * (-len(s) % 4), validate=True)


def hash_password(password: str) -> str:
    """The scrypt hash line field of ``password`` with a fresh 16-byte salt."""
    check_password(password)
    salt = secrets.token_bytes(16)
    key = hashlib.scrypt(password.encode(), salt=salt, n=SCRYPT_N, r=SCRYPT_R, p=SCRYPT_P,
                         dklen=32)
    return f"scrypt${SCRYPT_N}${SCRYPT_R}${SCRYPT_P}${_b64(salt)}${_b64(key)}"


def verify_password(password: str, hashed: str) -> bool:
    """Whether ``password`` matches ``hashed`` (constant-time compare); blocking (~50 ms)."""
    try:
        kind, n, r, p, salt, key = hashed.split("$")
        if kind != "scrypt" or len(password) > MAX_PASSWORD:
            return False
        want = _unb64(key)
        got = hashlib.scrypt(password.encode(), salt=_unb64(salt), n=int(n), r=int(r),
                             p=int(p), dklen=len(want), maxmem=64 << 20)
    except (ValueError, TypeError):
        return False
    return hmac.compare_digest(got, want)


def check_name(name: str) -> str:
    if not NAME_RE.fullmatch(name or ""):
        raise UsersError(f"user name {name!r}: 1 to 32 characters, lower-case letters, digits, "
                         "'_' or '-', starting with a letter")
    if name in RESERVED:
        raise UsersError(f"user name {name!r} is reserved ({', '.join(sorted(RESERVED))})")
    return name


def check_role(role: str) -> str:
    if role not in ROLES:
        raise UsersError(f"role {role!r}: expected one of {', '.join(ROLES)}")
    return role


def check_password(password: str) -> None:
    if not MIN_PASSWORD <= len(password) <= MAX_PASSWORD:
        raise UsersError(f"password: {MIN_PASSWORD} to {MAX_PASSWORD} characters")


def parse(text: str, where: str) -> dict[str, User]:
    """The accounts of a users file's text; ``UsersError`` naming ``where`` and the line."""
    users: dict[str, User] = {}
    for no, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split(":")
        if len(parts) != 3:
            raise UsersError(f"{where}:{no}: expected name:role:scrypt$N$r$p$salt$hash")
        name, role, hashed = parts
        try:
            check_name(name)
            check_role(role)
        except UsersError as e:
            raise UsersError(f"{where}:{no}: {e}") from None
        if not re.fullmatch(r"scrypt\$\d{1,8}\$\d{1,3}\$\d{1,3}\$[A-Za-z0-9+/]{8,}\$"
                            r"[A-Za-z0-9+/]{16,}", hashed):
            raise UsersError(f"{where}:{no}: the password of {name!r} is not a scrypt hash "
                             "(set it with rumba users passwd)")
        if name in users:
            raise UsersError(f"{where}:{no}: user {name!r} is listed twice")
        users[name] = User(name, role, hashed)
    return users


def read_users(path: Path) -> dict[str, User]:
    """The accounts in ``path`` (a missing file: none). Refused when others may read or write
    it, like the token file: the hashes are offline-guessable."""
    try:
        st = path.stat()
    except FileNotFoundError:
        return {}
    except OSError as e:
        raise UsersError(f"{path}: cannot read the users file: {e.strerror}") from None
    if not stat.S_ISREG(st.st_mode):
        raise UsersError(f"{path}: the users file is not a regular file")
    if stat.S_IMODE(st.st_mode) & 0o077:
        raise UsersError(f"{path}: the users file is readable by others (mode "
                         f"{stat.S_IMODE(st.st_mode):04o}); chmod 600 it")
    if st.st_size > MAX_FILE_BYTES:
        raise UsersError(f"{path}: the users file is larger than {MAX_FILE_BYTES} bytes")
    try:
        text = path.read_bytes().decode("utf-8")
    except OSError as e:
        raise UsersError(f"{path}: cannot read the users file: {e.strerror}") from None
    except UnicodeDecodeError:
        raise UsersError(f"{path}: the users file is not UTF-8 text") from None
    return parse(text, str(path))


def write_users(path: Path, users: dict[str, User]) -> None:
    """Replace ``path`` atomically (0600, fsync'd); comment lines of the old file are kept."""
    head: list[str] = []
    if path.is_file():
        head = [ln for ln in path.read_text(encoding="utf-8").splitlines()
                if ln.strip().startswith("#")]
    if not head:
        head = ["# rumba HMI accounts: name:role:password hash (roles: operator, engineer, admin)",
                "# edit with `rumba users add/passwd/remove/list --file <this file>`"]
    body = "\n".join(head + [f"{u.name}:{u.role}:{u.hash}" for u in users.values()]) + "\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".users-", dir=path.parent)  # created 0600
    try:
        os.write(fd, body.encode())
        os.fsync(fd)
        os.close(fd)
        os.replace(tmp, path)
    except BaseException:
        os.unlink(tmp)
        raise


class Accounts:
    """The accounts of one users file, read again whenever the file changes (mtime, size)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._seen: tuple[int, int] | None = None
        self._users = read_users(path)  # a bad file stops the daemon's start, naming it
        self._seen = self._stamp()

    def _stamp(self) -> tuple[int, int] | None:
        try:
            st = self.path.stat()
        except OSError:
            return None
        return st.st_mtime_ns, st.st_size

    def users(self) -> dict[str, User]:
        stamp = self._stamp()
        if stamp != self._seen:
            try:
                self._users = read_users(self.path)
            except UsersError:  # an edit gone wrong: nobody signs in until it is fixed
                self._users = {}
            self._seen = stamp
        return self._users

    def get(self, name: str) -> User | None:
        return self.users().get(name)

    def check(self, name: str, password: str) -> User | None:
        """The account when ``password`` is right (blocking: call it in a worker thread). An
        unknown name costs a hash too, so timing does not tell which names exist."""
        user = self.get(name)
        ok = verify_password(password, user.hash if user else _DUMMY)
        return user if ok and user is not None else None


_DUMMY = "scrypt$16384$8$1$AAAAAAAAAAAAAAAAAAAAAA$AAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAA"
