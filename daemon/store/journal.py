"""The run journal: one SQLite file (WAL) holding runs, every raw hit, centres, estimates,
verdicts and reports, with numbered schema migrations.

Raw data first, always: ``journal_hit`` commits each hit in its own transaction before the
session looks at it, so a ``kill -9`` (or, with ``synchronous=FULL``, a power cut) loses nothing
already received. Measured in ``benchmarks/bench_daemon.py``.
"""

from __future__ import annotations

import contextlib
import json
import re
import sqlite3
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from contracts.messages import ProbeHit
from contracts.yaml_files import ConfigError
from daemon.analysis.judge import Judgement
from daemon.analysis.result import Analysis
from daemon.store.schema import MIGRATIONS, SCHEMA_VERSION

FINAL_STATES = ("DONE", "ABORTED", "FAILED", "INTERRUPTED", "IMPORTED")
"""A run in any other state was cut short by a crash (marked INTERRUPTED on the next start)."""

Synchronous = Literal["FULL", "NORMAL"]


class StoreError(Exception):
    """The journal cannot be opened or used; the message is one line for the operator."""


class StoreOpenError(StoreError, ConfigError):
    """The journal cannot be created or opened (a ConfigError too: the CLI prints one line)."""


class RunIdError(StoreError, ConfigError):
    """A run id outside the safe charset (it names report files and reaches G-code)."""


RUN_ID_PATTERN = r"[A-Za-z0-9][A-Za-z0-9-]{0,63}"
"""Run ids: what ``daemon.run.session.new_run_id`` makes (letters, digits, '-'), 1-64 characters,
not starting with '-'. No '.', '/', '\\', space or line break: an id is safe as a file name, in a
URL and in a G-code comment."""
_RUN_ID = re.compile(RUN_ID_PATTERN)


def validate_run_id(run_id: str, where: str = "run id") -> str:
    """``run_id`` unchanged if it is safe, else ``RunIdError`` naming ``where`` (e.g.
    ``"log.csv: line 7: column run_id"``). fullmatch, never ``match`` with ``$``: ``$`` also
    matches before a trailing line break."""
    if not isinstance(run_id, str) or not _RUN_ID.fullmatch(run_id):
        raise RunIdError(f"{where}: invalid run id {run_id!r}: expected 1-64 letters, digits "
                         "or '-', starting with a letter or digit")
    return run_id


# The migrations live in daemon/store/schema.py (shared with the PostgreSQL fleet store).


def _why(e: OSError, directory: Path) -> str:
    # "File exists" is what mkdir says when a regular file is in the way: say that instead
    for p in (directory, *directory.parents):
        if p.exists() and not p.is_dir():
            return f"{p} is a file, not a directory"
    return e.strerror or str(e)


@dataclass(frozen=True)
class RunRow:
    id: str
    machine: str
    trigger: str
    state: str
    reason: str
    plan: str
    artefact: str
    dialect: str
    touch_total: int
    started_at: float
    ended_at: float | None
    verdict: str | None
    summary: str
    imported: bool
    hits: int = 0
    started_by: str = ""  # the HMI account that started it ('' : controller, panel, script)

    @property
    def final(self) -> bool:
        return self.state in FINAL_STATES


@dataclass(frozen=True)
class TrendPoint:
    """One completed run of a machine in its trend: when, its verdict, its analysis."""

    run_id: str
    started_at: float
    verdict: str
    analysis: Analysis


class Store:
    """The journal of one daemon. Single writer (the daemon's event loop); readers may be other
    processes (``rumba history``) thanks to WAL."""

    def __init__(self, path: Path | str, synchronous: Synchronous = "FULL",
                 source: str | None = None) -> None:
        """``source``: where the path was configured, e.g. ``"daemon.yaml: store.path"``; it
        prefixes an opening failure so the operator knows what to fix."""
        self.path = Path(path)
        where = source or str(self.path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise StoreOpenError(f"{where}: cannot create the journal directory "
                                 f"{self.path.parent}: {_why(e, self.path.parent)}") from None
        try:
            # Autocommit mode: every statement outside an explicit BEGIN is its own transaction.
            self.db = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
            mode = self.db.execute("PRAGMA journal_mode=WAL").fetchone()[0]
            if str(mode).lower() != "wal":
                raise StoreOpenError(f"{where}: cannot switch the journal {self.path} to WAL "
                                     f"(got {mode})")
            self.db.execute(f"PRAGMA synchronous={'FULL' if synchronous == 'FULL' else 'NORMAL'}")
            self.db.execute("PRAGMA foreign_keys=ON")
            self.db.execute("PRAGMA busy_timeout=5000")
            self._migrate()
        except sqlite3.Error as e:
            raise StoreOpenError(f"{where}: cannot open the journal {self.path}: {e}") from None

    # ------------------------------------------------------------------------------- schema
    def _migrate(self) -> None:
        self.db.execute("CREATE TABLE IF NOT EXISTS schema_version "
                        "(version INTEGER PRIMARY KEY, applied_at REAL NOT NULL)")
        current = self.schema_version()
        if current > SCHEMA_VERSION:
            raise StoreError(f"{self.path}: journal schema v{current} is newer than this rumba "
                             f"(v{SCHEMA_VERSION}); upgrade rumba")
        for version in range(current + 1, SCHEMA_VERSION + 1):
            self.db.execute("BEGIN IMMEDIATE")
            try:
                for stmt in MIGRATIONS[version - 1]:
                    self.db.execute(stmt)
                self.db.execute("INSERT INTO schema_version VALUES (?, ?)", (version, time.time()))
                self.db.execute("COMMIT")
            except BaseException:
                self.db.execute("ROLLBACK")
                raise

    def schema_version(self) -> int:
        row = self.db.execute("SELECT MAX(version) FROM schema_version").fetchone()
        return int(row[0] or 0)

    def close(self) -> None:
        self.db.close()

    @contextlib.contextmanager
    def transaction(self) -> Iterator[None]:
        """All or nothing: the writes inside are committed together or not at all. Nested
        calls join the outer transaction (so bulk writers can be grouped)."""
        if self.db.in_transaction:
            yield
            return
        self.db.execute("BEGIN IMMEDIATE")
        try:
            yield
        except BaseException:
            self.db.execute("ROLLBACK")
            raise
        self.db.execute("COMMIT")

    # --------------------------------------------------------------------------------- runs
    def new_run(self, run_id: str, machine: str, trigger: str, *, plan: str = "",
                artefact: str = "", dialect: str = "", touch_total: int = 0,
                state: str = "PREPARE", imported: bool = False,
                started_at: float | None = None, started_by: str = "") -> None:
        validate_run_id(run_id)
        if self.db.execute("SELECT 1 FROM runs WHERE id=?", (run_id,)).fetchone():
            raise StoreError(f"run {run_id} is already in the journal {self.path}")
        self.db.execute(
            "INSERT INTO runs (id, machine, trigger, state, plan, artefact, dialect, touch_total,"
            " started_at, imported, started_by) VALUES (?,?,?,?,?,?,?,?,?,?,?)",
            (run_id, machine, trigger, state, plan, artefact, dialect, touch_total,
             time.time() if started_at is None else started_at, int(imported), started_by))

    def set_state(self, run_id: str, state: str, reason: str | None = None, *,
                  touch_total: int | None = None) -> None:
        validate_run_id(run_id)
        ended = time.time() if state in FINAL_STATES else None
        self.db.execute(
            "UPDATE runs SET state=?, reason=COALESCE(?, reason), ended_at=COALESCE(?, ended_at),"
            " touch_total=COALESCE(?, touch_total) WHERE id=?",
            (state, reason, ended, touch_total, run_id))

    def mark_interrupted(self) -> list[str]:
        """Runs left in a non-final state by a crash → INTERRUPTED (their hits stay)."""
        rows = self.db.execute(
            f"SELECT id FROM runs WHERE state NOT IN ({','.join('?' * len(FINAL_STATES))})",
            FINAL_STATES).fetchall()
        ids = [r[0] for r in rows]
        for run_id in ids:
            state = self.run(run_id).state
            self.set_state(run_id, "INTERRUPTED",
                           f"daemon stopped unexpectedly during {state}; "
                           f"{self.hit_count(run_id)} hits kept")
        return ids

    def run(self, run_id: str) -> RunRow:
        validate_run_id(run_id)
        rows = self._runs("WHERE r.id = ?", (run_id,))
        if not rows:
            raise StoreError(f"no run {run_id!r} in {self.path}")
        return rows[0]

    def runs(self, machine: str | None = None, limit: int = 50) -> list[RunRow]:
        """Most recent first."""
        if machine is None:
            return self._runs("ORDER BY r.started_at DESC LIMIT ?", (limit,))
        return self._runs("WHERE r.machine = ? ORDER BY r.started_at DESC LIMIT ?",
                          (machine, limit))

    def _runs(self, where: str, args: tuple) -> list[RunRow]:
        q = ("SELECT r.id, r.machine, r.trigger, r.state, r.reason, r.plan, r.artefact, r.dialect,"
             " r.touch_total, r.started_at, r.ended_at, r.verdict, r.summary, r.imported,"
             " (SELECT COUNT(*) FROM hits h WHERE h.run_id = r.id), r.started_by FROM runs r "
             + where)
        return [RunRow(*row[:13], bool(row[13]), row[14], row[15])
                for row in self.db.execute(q, args)]

    # --------------------------------------------------------------------------------- hits
    def journal_hit(self, run_id: str, hit: ProbeHit) -> None:
        """Commit one hit now (its own transaction): raw data first, before anything else."""
        validate_run_id(run_id)
        self.db.execute(
            "INSERT INTO hits VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?)",
            (run_id, hit.seq, hit.t_s, hit.repeat, hit.pose, hit.b_cmd_deg, hit.c_cmd_deg,
             hit.ball, hit.touch, *map(float, hit.direction), json.dumps(hit.axes),
             int(hit.triggered), hit.feed_mm_min, hit.raw, json.dumps(hit.extra), time.time()))

    def journal_hits(self, run_id: str, hits: Iterable[ProbeHit]) -> int:
        """Bulk insert in one transaction (imports only, never live capture)."""
        n = 0
        with self.transaction():
            for hit in hits:
                self.journal_hit(run_id, hit)
                n += 1
        return n

    def hit_count(self, run_id: str) -> int:
        return int(self.db.execute("SELECT COUNT(*) FROM hits WHERE run_id=?",
                                   (run_id,)).fetchone()[0])

    def hits(self, run_id: str) -> list[ProbeHit]:
        validate_run_id(run_id)
        rows = self.db.execute(
            "SELECT seq, t_s, repeat, pose, b_cmd_deg, c_cmd_deg, ball, touch, dir_x, dir_y,"
            " dir_z, axes, triggered, feed_mm_min, raw, extra FROM hits WHERE run_id=?"
            " ORDER BY seq", (run_id,))
        return [ProbeHit(seq=r[0], pose=r[3], ball=r[6], touch=r[7], axes=json.loads(r[11]),
                         triggered=bool(r[12]), t_s=r[1], repeat=r[2], raw=r[14],
                         b_cmd_deg=r[4], c_cmd_deg=r[5], direction=(r[8], r[9], r[10]),
                         feed_mm_min=r[13], extra=json.loads(r[15])) for r in rows]

    # ----------------------------------------------------------------------------- results
    def save_centres(self, run_id: str, rows: Iterable[tuple]) -> None:
        """rows: (pose, ball, b_deg, c_deg, x_mm, y_mm, z_mm, radius_dev_um, form_um)."""
        validate_run_id(run_id)
        with self.transaction():
            self.db.executemany("INSERT OR REPLACE INTO centres VALUES (?,?,?,?,?,?,?,?,?,?)",
                                [(run_id, *r) for r in rows])

    def centres(self, run_id: str) -> list[tuple]:
        return self.db.execute(
            "SELECT pose, ball, b_deg, c_deg, x_mm, y_mm, z_mm, radius_dev_um, form_um"
            " FROM centres WHERE run_id=? ORDER BY pose, ball", (run_id,)).fetchall()

    def save_analysis(self, run_id: str, analysis: Analysis) -> None:
        """Stored as its JSON (``Analysis.to_json``): the journal's format stays text."""
        validate_run_id(run_id)
        self.db.execute("INSERT OR REPLACE INTO estimates VALUES (?, ?)",
                        (run_id, json.dumps(analysis.to_json())))

    def analysis(self, run_id: str) -> Analysis | None:
        row = self.db.execute("SELECT analysis FROM estimates WHERE run_id=?",
                              (run_id,)).fetchone()
        return Analysis.from_json(json.loads(row[0])) if row else None

    def save_judgement(self, run_id: str, j: Judgement) -> None:
        """The verdict of a run as the judge gave it (status, reasons, checks, summary)."""
        self.save_verdict(run_id, j.status, list(j.reasons), [c.as_dict() for c in j.checks],
                          j.summary)

    def save_verdict(self, run_id: str, status: str, reasons: list[str],
                     checks: list[dict[str, Any]], summary: str) -> None:
        validate_run_id(run_id)
        with self.transaction():
            self.db.execute("INSERT OR REPLACE INTO verdicts VALUES (?,?,?,?,0)",
                            (run_id, status, json.dumps(reasons), json.dumps(checks)))
            self.db.execute("UPDATE runs SET verdict=?, summary=? WHERE id=?",
                            (status, summary, run_id))

    def mark_written_back(self, run_id: str) -> None:
        validate_run_id(run_id)
        self.db.execute("UPDATE verdicts SET written_back=1 WHERE run_id=?", (run_id,))

    def verdict(self, run_id: str) -> dict[str, Any] | None:
        row = self.db.execute("SELECT status, reasons, checks, written_back FROM verdicts"
                              " WHERE run_id=?", (run_id,)).fetchone()
        if row is None:
            return None
        return {"status": row[0], "reasons": json.loads(row[1]), "checks": json.loads(row[2]),
                "written_back": bool(row[3])}

    def save_report(self, run_id: str, html_path: Path, json_path: Path) -> None:
        validate_run_id(run_id)
        self.db.execute("INSERT OR REPLACE INTO reports VALUES (?,?,?)",
                        (run_id, str(html_path), str(json_path)))

    def report(self, run_id: str) -> tuple[Path, Path] | None:
        validate_run_id(run_id)
        row = self.db.execute("SELECT html_path, json_path FROM reports WHERE run_id=?",
                              (run_id,)).fetchone()
        return (Path(row[0]), Path(row[1])) if row else None

    def last_good(self, machine: str, before: str | None = None
                  ) -> tuple[str, Analysis] | None:
        """The most recent PASS run of ``machine`` with its analysis (the drift reference)."""
        q = ("SELECT r.id, e.analysis FROM runs r JOIN estimates e ON e.run_id = r.id"
             " WHERE r.machine=? AND r.verdict='PASS' AND r.state='DONE'")
        args: tuple = (machine,)
        if before is not None:
            q += " AND r.id != ?"
            args += (before,)
        row = self.db.execute(q + " ORDER BY r.started_at DESC LIMIT 1", args).fetchone()
        return (row[0], Analysis.from_json(json.loads(row[1]))) if row else None

    def trend(self, machine: str, limit: int = 30) -> list[TrendPoint]:
        """Completed runs with an analysis, oldest first."""
        rows = self.db.execute(
            "SELECT r.id, r.started_at, r.verdict, e.analysis FROM runs r"
            " JOIN estimates e ON e.run_id = r.id WHERE r.machine=? AND r.verdict IS NOT NULL"
            " ORDER BY r.started_at DESC LIMIT ?", (machine, limit)).fetchall()
        return [TrendPoint(r[0], r[1], r[2], Analysis.from_json(json.loads(r[3])))
                for r in reversed(rows)]

    # ------------------------------------------------------------------------- HMI sessions
    def revoke_hmi_session(self, session_id: str, expires_at: float) -> None:
        self.db.execute("INSERT OR REPLACE INTO hmi_revoked VALUES (?, ?)",
                        (session_id, expires_at))

    def revoked_hmi_sessions(self) -> dict[str, float]:
        """Signed-out session ids → expiry; forgets those expired (their cookies are dead)."""
        self.db.execute("DELETE FROM hmi_revoked WHERE expires_at < ?", (time.time(),))
        return dict(self.db.execute("SELECT session_id, expires_at FROM hmi_revoked"))
