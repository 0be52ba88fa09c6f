"""Where the journal lives, from ``store.url`` in daemon.yaml: ``sqlite:///path`` (the embedded
journal, the default) or ``postgresql://…`` (the fleet store, with the local journal as buffer)."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from contracts.yaml_files import ConfigError

PG_SCHEMES = ("postgresql://", "postgres://")


@dataclass(frozen=True)
class StoreUrl:
    """``kind`` "sqlite" (``path`` is the journal) or "postgresql" (``dsn`` is the libpq URL of
    the fleet store; the daemon still journals to its local file first)."""

    kind: str
    path: Path | None = None
    dsn: str | None = None

    @property
    def redacted(self) -> str:
        return redact(self.dsn) if self.dsn else f"sqlite:///{self.path}"


def redact(dsn: str) -> str:
    """The URL without its password, for logs and error messages."""
    return re.sub(r"(://[^:/@]+):[^@/]*@", r"\1:***@", dsn)


def parse_store_url(url: str, where: str) -> StoreUrl:
    """``sqlite:///rel/or/abs.sqlite`` (three slashes, the path after them; ``sqlite:////abs``
    is absolute) or ``postgresql://user@host:port/db?sslmode=…`` (libpq's URL, parsed by libpq
    itself so every libpq parameter works: ``passfile``, ``sslmode``, ``sslrootcert`` …)."""
    if url.startswith("sqlite:///"):
        rest = url[len("sqlite:///"):]
        if not rest:
            raise ConfigError(f"{where}: sqlite URL without a path (sqlite:///rumba.sqlite)")
        return StoreUrl("sqlite", path=Path(rest))
    if url.startswith(PG_SCHEMES):
        from psycopg import conninfo

        try:
            params = conninfo.conninfo_to_dict(url)
        except Exception as e:  # psycopg.ProgrammingError: libpq's own message
            raise ConfigError(f"{where}: invalid PostgreSQL URL {redact(url)}: "
                              f"{' '.join(str(e).split())}") from None
        if params.get("password"):
            raise ConfigError(f"{where}: the PostgreSQL URL carries a password; put it in a "
                              "libpq password file instead (?passfile=/etc/rumba/pgpass, mode "
                              "600) so daemon.yaml holds no secret")
        return StoreUrl("postgresql", dsn=url)
    raise ConfigError(f"{where}: unsupported store URL {redact(url)!r}: expected "
                      "sqlite:///path or postgresql://user@host/db")
