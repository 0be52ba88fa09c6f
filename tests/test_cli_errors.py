"""The rumba command's last resort: a defect ends as one line naming a crash file, exit 70."""

from __future__ import annotations

from pathlib import Path

import pytest

import daemon.cli.commands.history as history
from daemon.cli.main import EX_SOFTWARE, main


def test_internal_error_is_one_line_with_a_crash_file(tmp_path: Path, monkeypatch,
                                                      capsys) -> None:
    def boom(args):  # a defect inside a subcommand, not bad input
        raise ZeroDivisionError("division by zero in the middle of nowhere")

    monkeypatch.delenv("RUMBA_DEBUG", raising=False)
    monkeypatch.setenv("RUMBA_CRASH_DIR", str(tmp_path))
    monkeypatch.setattr(history, "cmd_history", boom)
    (tmp_path / "none.yaml").write_text("")  # an existing file: past the arguments' check
    code = main(["history", "--config", str(tmp_path / "none.yaml")])
    err = capsys.readouterr().err
    assert code == EX_SOFTWARE
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: internal error in rumba-cnc")
    assert "Traceback" not in err and "ZeroDivisionError" not in err
    crashes = list(tmp_path.glob("rumba-crash-*.txt"))
    assert len(crashes) == 1 and str(crashes[0]) in err
    assert "ZeroDivisionError" in crashes[0].read_text()


def test_debug_lets_the_defect_through(tmp_path: Path, monkeypatch) -> None:
    def boom(args):
        raise ZeroDivisionError("x")

    monkeypatch.setenv("RUMBA_DEBUG", "1")
    monkeypatch.setattr(history, "cmd_history", boom)
    (tmp_path / "none.yaml").write_text("")
    with pytest.raises(ZeroDivisionError):
        main(["history", "--config", str(tmp_path / "none.yaml")])
