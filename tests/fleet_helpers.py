"""Module-scoped real PostgreSQL / mosquitto for the fleet tests, and a condition wait."""

from __future__ import annotations

import asyncio
import itertools
import time
from collections.abc import Callable, Iterator

import psycopg
import pytest

from simulators.fleet_peers import MosquittoPeer, PeerUnavailable, PostgresPeer

_db_names = itertools.count()


def start_postgres() -> PostgresPeer:
    try:
        return PostgresPeer()
    except PeerUnavailable as e:
        pytest.skip(str(e))


@pytest.fixture(scope="module")
def pg() -> Iterator[PostgresPeer]:
    """The test module's real PostgreSQL on loopback, stopped after its last test (import it
    into the module; each test takes a ``fresh_db`` of it)."""
    peer = start_postgres()
    try:
        yield peer
    finally:
        peer.close()


def start_mosquitto(**kw) -> MosquittoPeer:  # type: ignore[no-untyped-def]
    try:
        return MosquittoPeer(**kw)
    except PeerUnavailable as e:
        pytest.skip(str(e))


def fresh_db(pg: PostgresPeer) -> str:
    """A new empty database on the module's server: tests never see each other's rows."""
    name = f"t{next(_db_names)}_{int(time.time() * 1000) % 10**8}"
    with psycopg.connect(pg.dsn, autocommit=True) as c:
        c.execute(f"CREATE DATABASE {name}")  # type: ignore[arg-type]
    return pg.dsn.rsplit("/", 1)[0] + "/" + name


async def until(cond: Callable[[], bool], timeout_s: float = 30.0, what: str = "") -> None:
    """Wait for a condition (a readiness check, never a fixed delay)."""
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what or cond}")
        await asyncio.sleep(0.02)
