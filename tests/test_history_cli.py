"""`rumba history --import` is all or nothing and never writes outside the reports directory;
a journal that cannot be created is one `error:` line (exit 2) for every command opening it."""

from __future__ import annotations

import dataclasses
import sqlite3

import numpy as np
import pytest

from benchmarks.rigs.daemon_helpers import thesis_rows, thesis_setup, write_daemon_yaml
from contracts.probing_log import write_log
from daemon.analysis.pipeline import PipelineError
from daemon.cli.main import main as cli_main
from identification.spherefit import SphereFitError


def run_cli(argv: list[str], capsys) -> tuple[int, str, str]:
    code = cli_main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def one_error_line(err: str) -> str:
    assert err.startswith("error: ") and err.count("\n") == 1, err
    assert "Traceback" not in err
    return err


def journal_runs(tmp_path) -> list[tuple]:
    db = tmp_path / "journal.sqlite"
    if not db.exists():
        return []
    con = sqlite3.connect(db)
    try:
        runs = con.execute("SELECT id, state FROM runs").fetchall()
        hits = con.execute("SELECT COUNT(*) FROM hits").fetchone()[0]
    finally:
        con.close()
    return runs + ([("hits", hits)] if hits else [])


@pytest.fixture(scope="module")
def rows():
    return thesis_rows(thesis_setup())


@pytest.mark.parametrize("run_id", ["../PWNED", "../../x/PWNED", "PWNED.x"])
def test_import_refuses_a_run_id_that_leaves_the_reports_dir(tmp_path, capsys, rows, run_id):
    cfg = write_daemon_yaml(tmp_path)  # reports in tmp_path/reports: ../PWNED.html would land
    log = tmp_path / "evil.csv"        # in tmp_path, which exists
    write_log(log, [dataclasses.replace(r, run_id=run_id) for r in rows])
    code, out, err = run_cli(["history", "--config", str(cfg), "--import", str(log),
                              "--machine", "mill1"], capsys)
    assert code == 2 and out == ""
    one_error_line(err)
    assert f"{log}: column run_id: invalid run id {run_id!r}" in err
    assert not list(tmp_path.rglob("PWNED*")) and not (tmp_path / "x").exists()
    assert journal_runs(tmp_path) == []


@pytest.mark.parametrize("error", [SphereFitError("degenerate point sets in groups [27]"),
                                   np.linalg.LinAlgError("SVD did not converge"),
                                   PipelineError("identification impossible: rank-deficient")])
def test_any_analysis_failure_is_one_line_and_journals_nothing(tmp_path, capsys, rows,
                                                               monkeypatch, error):
    """Whatever the analysis raises on bad data (the log reader may not catch every absurd
    value), the import ends as one line and the journal stays as it was: the sphere fit's
    failures are turned into a PipelineError by the pipeline itself."""
    import daemon.analysis.pipeline as pipeline

    def failing(*_a: object, **_k: object) -> None:
        raise error

    step = "analyse_centres" if isinstance(error, PipelineError) else "rows_to_centres"
    monkeypatch.setattr(pipeline, step, failing)
    cfg = write_daemon_yaml(tmp_path)
    log = tmp_path / "in.csv"
    write_log(log, rows)
    code, out, err = run_cli(["history", "--config", str(cfg), "--import", str(log),
                              "--machine", "mill1"], capsys)
    assert code == 2 and out == ""
    assert f"{log}: run synth: analysis failed: {error}; nothing imported" in one_error_line(err)
    assert journal_runs(tmp_path) == []


def test_bad_row_at_the_end_imports_nothing_then_the_corrected_file_imports(
        tmp_path, capsys, rows):
    cfg = write_daemon_yaml(tmp_path)
    log = tmp_path / "in.csv"
    # last row: same seq as the first one (the journal keys hits by seq); refused by the log
    # reader or by the journal, either way before anything is kept
    write_log(log, [*rows[:-1], dataclasses.replace(rows[-1], seq=rows[0].seq)])
    argv = ["history", "--config", str(cfg), "--import", str(log), "--machine", "mill1"]
    for extra in (["--no-analyse"], []):
        code, out, err = run_cli([*argv, *extra], capsys)
        assert code == 2 and out == ""
        assert str(log) in one_error_line(err)
        assert journal_runs(tmp_path) == []
    write_log(log, rows)  # corrected
    code, out, err = run_cli(argv, capsys)
    assert code == 0, err
    assert "imported run synth: 140 touches" in out and "report: " in out
    assert journal_runs(tmp_path) == [("synth", "DONE"), ("hits", 140)]
    assert (tmp_path / "reports" / "synth.html").is_file()
    assert (tmp_path / "reports" / "synth.json").is_file()
    for name in ("synth.json", "synth.pdf", "synth.html"):  # every file written is named
        assert (tmp_path / "reports" / name).is_file() and name in out


def test_failed_analysis_journals_nothing_so_the_complete_file_imports(tmp_path, capsys, rows):
    """A log cut after the first pose is read fine but cannot be identified: before, the run
    stayed in the journal (FAILED, with its hits) and blocked the complete log."""
    cfg = write_daemon_yaml(tmp_path)
    log = tmp_path / "in.csv"
    write_log(log, [r for r in rows if r.pose == 0])
    argv = ["history", "--config", str(cfg), "--import", str(log), "--machine", "mill1"]
    code, out, err = run_cli(argv, capsys)
    assert code == 2 and out == ""
    one_error_line(err)
    assert f"{log}: run synth: analysis failed: identification impossible" in err
    assert "nothing imported (use --no-analyse" in err
    assert journal_runs(tmp_path) == []
    write_log(log, rows)
    code, out, err = run_cli(argv, capsys)
    assert code == 0, err
    assert journal_runs(tmp_path) == [("synth", "DONE"), ("hits", 140)]


@pytest.mark.parametrize("value", [1e15, 1e308])
def test_absurd_coordinate_is_one_line_and_journals_nothing(tmp_path, capsys, rows, value):
    cfg = write_daemon_yaml(tmp_path)
    log = tmp_path / "in.csv"
    write_log(log, [*rows[:-1], dataclasses.replace(rows[-1], x_mm=value)])
    argv = ["history", "--config", str(cfg), "--import", str(log), "--machine", "mill1"]
    code, out, err = run_cli(argv, capsys)
    assert code == 2 and out == ""
    assert str(log) in one_error_line(err)
    assert journal_runs(tmp_path) == []
    write_log(log, rows)
    code, out, err = run_cli([*argv, "--no-analyse"], capsys)
    assert code == 0 and "imported run synth: 140 touches" in out, err


@pytest.mark.parametrize("command", [["history"], ["run"]])
@pytest.mark.parametrize("under", ["afile/journal.sqlite", "afile/sub/journal.sqlite"])
def test_journal_under_a_regular_file_is_one_line(tmp_path, capsys, command, under):
    cfg = write_daemon_yaml(tmp_path)
    (tmp_path / "afile").write_text("not a directory")
    cfg.write_text(cfg.read_text().replace(str(tmp_path / "journal.sqlite"),
                                           str(tmp_path / under)))
    code, _, err = run_cli([*command, "--config", str(cfg)], capsys)
    assert code == 2
    one_error_line(err)
    assert err.startswith(f"error: {cfg}: store.path: cannot create the journal directory")
    assert f"{tmp_path / 'afile'} is a file, not a directory" in err
