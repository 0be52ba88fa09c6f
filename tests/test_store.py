"""The journal: WAL, migrations, per-hit durability against kill -9, interrupted runs, CSV."""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import time

import pytest

from benchmarks.rigs.daemon_helpers import thesis_rows, thesis_setup
from contracts.probing_log import read_log
from daemon.store.journal import SCHEMA_VERSION, Store, StoreError
from daemon.store.probing_csv import export_csv, import_csv
from tests.store_helpers import hit


def test_wal_and_schema_version(tmp_path):
    s = Store(tmp_path / "j.sqlite")
    assert s.db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    assert s.db.execute("PRAGMA synchronous").fetchone()[0] == 2  # FULL
    assert s.schema_version() == SCHEMA_VERSION
    s.close()
    s = Store(tmp_path / "j.sqlite", synchronous="NORMAL")  # reopening migrates nothing
    assert s.db.execute("SELECT COUNT(*) FROM schema_version").fetchone()[0] == SCHEMA_VERSION
    s.close()


def test_newer_schema_is_refused(tmp_path):
    Store(tmp_path / "j.sqlite").close()
    db = sqlite3.connect(tmp_path / "j.sqlite")
    db.execute("INSERT INTO schema_version VALUES (99, 0)")
    db.commit()
    db.close()
    with pytest.raises(StoreError, match="schema v99 is newer"):
        Store(tmp_path / "j.sqlite")


def test_hit_round_trip_and_interrupted(tmp_path):
    s = Store(tmp_path / "j.sqlite")
    s.new_run("R1", "mill1", "cnc", touch_total=3)
    s.set_state("R1", "CAPTURE")
    for k in (1, 2):
        s.journal_hit("R1", hit(k))
    s.journal_hit("R1", hit(3, triggered=False))
    assert s.hits("R1") == [hit(1), hit(2), hit(3, triggered=False)]
    with pytest.raises(sqlite3.IntegrityError):
        s.journal_hit("R1", hit(2))  # a seq is journaled once
    s.new_run("R2", "mill1", "hmi")
    s.set_state("R2", "DONE")
    assert s.mark_interrupted() == ["R1"]
    r = s.run("R1")
    assert r.state == "INTERRUPTED" and r.hits == 3 and "during CAPTURE" in r.reason
    assert r.ended_at is not None and s.run("R2").state == "DONE"
    assert s.mark_interrupted() == []
    with pytest.raises(StoreError, match="no run 'R9'"):
        s.run("R9")


_WRITER = """
import sys, time
from daemon.store.journal import Store
from tests.store_helpers import hit
s = Store(sys.argv[1], synchronous=sys.argv[2])
s.new_run("K", "mill1", "cnc")
for k in range(1, 100000):
    s.journal_hit("K", hit(k))
    print(k, flush=True)  # reported only after the commit returned
"""


@pytest.mark.parametrize("sync", ["FULL", "NORMAL"])
def test_kill_9_loses_no_committed_hit(tmp_path, sync):
    """A writer is SIGKILLed mid-stream: every hit it reported as journaled is in the file."""
    db = tmp_path / "j.sqlite"
    p = subprocess.Popen([sys.executable, "-c", _WRITER, str(db), sync],
                         stdout=subprocess.PIPE, text=True, cwd=os.getcwd())
    last = 0
    deadline = time.monotonic() + 30
    while last < 200 and time.monotonic() < deadline:
        last = int(p.stdout.readline())
    os.kill(p.pid, signal.SIGKILL)
    p.wait()
    s = Store(db)
    n = s.hit_count("K")
    assert n >= last >= 200
    assert [h.seq for h in s.hits("K")] == list(range(1, n + 1))
    assert s.mark_interrupted() == ["K"]
    s.close()


def test_csv_export_import_round_trip(tmp_path):
    setup = thesis_setup()
    rows = thesis_rows(setup)
    s = Store(tmp_path / "j.sqlite")
    csv = tmp_path / "log.csv"
    from contracts.probing_log import write_log
    write_log(csv, rows)
    run_id, n = import_csv(s, csv, "mill1", setup.machine, setup.artefact)
    assert (run_id, n) == ("synth", len(rows))
    assert s.run(run_id).imported and s.run(run_id).trigger == "import"
    with pytest.raises(StoreError, match="already in the journal"):
        import_csv(s, csv, "mill1", setup.machine, setup.artefact)
    out = tmp_path / "out.csv"
    assert export_csv(s, run_id, out, setup.machine) == len(rows)
    assert read_log(out, setup.artefact) == rows  # bit-exact round trip
    assert csv.read_text() == out.read_text()
    with pytest.raises(StoreError):
        export_csv(s, "nope", out, setup.machine)


def test_import_is_all_or_nothing(tmp_path, monkeypatch):
    """A row the journal refuses (here: a seq already used, let through by a stubbed log
    reader) leaves no half-imported run behind, so the corrected log imports."""
    import dataclasses

    import daemon.store.probing_csv

    setup = thesis_setup()
    rows = thesis_rows(setup)
    bad = [*rows[:-1], dataclasses.replace(rows[-1], seq=rows[0].seq)]
    monkeypatch.setattr(daemon.store.probing_csv, "read_log", lambda path, artefact: bad)
    s = Store(tmp_path / "j.sqlite")
    with pytest.raises(StoreError, match="refuses run synth"):
        import_csv(s, tmp_path / "log.csv", "mill1", setup.machine, setup.artefact)
    assert s.runs() == [] and s.db.execute("SELECT COUNT(*) FROM hits").fetchone()[0] == 0
    monkeypatch.setattr(daemon.store.probing_csv, "read_log", lambda path, artefact: rows)
    assert import_csv(s, tmp_path / "log.csv", "mill1", setup.machine,
                      setup.artefact) == ("synth", len(rows))
    s.close()
