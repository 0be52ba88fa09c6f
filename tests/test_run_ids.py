"""Run ids and file names from data: one safe charset, refused by the store at every entry, and
every path built from data proven to stay in its directory."""

from __future__ import annotations

import os

import pytest

from contracts.messages import ProbeHit
from contracts.yaml_files import ConfigError
from daemon.run.session import new_run_id
from daemon.safepath import UnsafePathError, contained_path, plain_name
from daemon.store.journal import RunIdError, Store, StoreError, validate_run_id

BAD_IDS = ["../../x/PWNED", "a/b", "a\\b", "..", ".", "", "-x", "run\n", "run\nx", "a b",
           "a.html", "x" * 65, "/etc/passwd", "C:x", "r\x00", "ré"]


@pytest.mark.parametrize("run_id", ["synth", "R1", "example-annexB", "x" * 64,
                                    "20200101T000000Z-0a0a"])
def test_good_run_ids(run_id):
    assert validate_run_id(run_id) == run_id


@pytest.mark.parametrize("run_id", BAD_IDS)
def test_bad_run_ids_are_refused_with_one_line(run_id):
    with pytest.raises(RunIdError) as e:
        validate_run_id(run_id, "log.csv: column run_id")
    msg = str(e.value)
    assert msg.startswith("log.csv: column run_id: invalid run id") and "\n" not in msg
    assert "expected 1-64 letters, digits or '-'" in msg
    # caught by `rumba` (one line, exit 2) and by code that handles the journal's errors
    assert isinstance(e.value, ConfigError) and isinstance(e.value, StoreError)


def test_new_run_id_is_in_the_charset():
    rid = new_run_id()
    assert validate_run_id(rid) == rid and len(rid) == 29


@pytest.mark.parametrize("run_id", ["../../x/PWNED", "a.b", "r\n"])
def test_store_refuses_bad_run_ids_at_every_entry(tmp_path, run_id):
    s = Store(tmp_path / "j.sqlite")
    hit = ProbeHit(seq=1, pose=0, ball="B1", touch=1, axes={"X": 1.0}, triggered=True)
    calls = [
        lambda: s.new_run(run_id, "mill1", "cnc"),
        lambda: s.set_state(run_id, "DONE"),
        lambda: s.journal_hit(run_id, hit),
        lambda: s.journal_hits(run_id, [hit]),
        lambda: s.save_centres(run_id, []),
        lambda: s.save_analysis(run_id, {}),
        lambda: s.save_verdict(run_id, "PASS", [], [], ""),
        lambda: s.mark_written_back(run_id),
        lambda: s.save_report(run_id, tmp_path / "a.html", tmp_path / "a.json"),
        lambda: s.run(run_id),
        lambda: s.hits(run_id),
        lambda: s.report(run_id),
    ]
    for call in calls:
        with pytest.raises(RunIdError):
            call()
    assert s.db.execute("SELECT COUNT(*) FROM runs").fetchone()[0] == 0
    assert s.db.execute("SELECT COUNT(*) FROM hits").fetchone()[0] == 0
    s.close()


def test_transaction_is_all_or_nothing_and_nests(tmp_path):
    s = Store(tmp_path / "j.sqlite")
    with pytest.raises(RuntimeError), s.transaction():
        s.new_run("A", "mill1", "cnc")
        s.save_verdict("A", "PASS", [], [], "ok")  # nested transaction joins the outer one
        raise RuntimeError
    assert s.runs() == []
    with s.transaction():
        s.new_run("A", "mill1", "cnc")
    assert [r.id for r in s.runs()] == ["A"]
    with pytest.raises(StoreError, match="run A is already in the journal"):
        s.new_run("A", "mill1", "cnc")
    s.close()


@pytest.mark.parametrize("name", ["../x.html", "a/b.html", "..", ".", "", "/etc/passwd",
                                  "a\\b.html", "C:x.html", "x\x00.html", "x\n.html"])
def test_contained_path_refuses_names_that_leave_the_directory(tmp_path, name):
    with pytest.raises(UnsafePathError) as e:
        contained_path(tmp_path, name)
    assert "\n" not in str(e.value).replace(repr(name), "")
    with pytest.raises(UnsafePathError):
        plain_name(name)


def test_contained_path_accepts_plain_names_and_refuses_symlink_escapes(tmp_path):
    base = tmp_path / "reports"
    base.mkdir()
    assert contained_path(base, "R1.html") == base / "R1.html"
    outside = tmp_path / "outside"
    outside.mkdir()
    os.symlink(outside / "R2.html", base / "R2.html")  # planted: would write outside
    with pytest.raises(UnsafePathError, match="outside this directory"):
        contained_path(base, "R2.html")
    os.symlink(outside, tmp_path / "link")  # a base that is itself a symlink is fine
    assert contained_path(tmp_path / "link", "R3.html") == tmp_path / "link" / "R3.html"


def test_prepare_refuses_an_auxiliary_file_name_that_leaves_its_directory(monkeypatch):
    """Aux files (Heidenhain format files) become files on the controller and next to
    `rumba gcode -o`; a name with a separator is refused before anything is sent."""
    from benchmarks.rigs.daemon_helpers import thesis_setup
    from daemon.analysis import pipeline
    from programs import dialects

    setup = thesis_setup()
    cls = type(dialects.get_dialect(setup.dialect))
    monkeypatch.setattr(cls, "aux_files", lambda self, prog: {"../RUMBA_B1.A": "x"})
    with pytest.raises(pipeline.PipelineError, match=r"refusing '\.\./RUMBA_B1\.A'"):
        pipeline.prepare(setup, "R1")
