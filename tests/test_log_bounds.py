"""The daemon's log cannot fill a disk (daemon/service/logs.py): a message that repeats is
counted, not repeated, and ``rumba run --log-file`` rotates at its size."""

from __future__ import annotations

import io
import logging
import subprocess
import sys
import textwrap

from daemon.service.logs import RepeatFilter
from tests.stop_helpers import ROOT


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def _logger(repeats: RepeatFilter) -> tuple[logging.Logger, io.StringIO]:
    out = io.StringIO()
    handler = logging.StreamHandler(out)
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    handler.addFilter(repeats)
    lg = logging.getLogger(f"rumba.test-repeats.{id(out)}")
    lg.propagate = False
    lg.handlers = [handler]
    lg.setLevel(logging.DEBUG)
    return lg, out


def _callback_fails() -> None:
    raise AssertionError("Write buffer should not be empty")


def _word(i: int) -> str:
    """``i`` in letters (a message whose words, not only numbers, differ)."""
    return "".join(chr(97 + int(d)) for d in str(i))


def test_a_flood_of_one_traceback_is_logged_once_then_counted():
    clock = Clock()
    repeats = RepeatFilter(window_s=60, clock=clock)
    lg, out = _logger(repeats)
    for i in range(10_000):  # the loop's exception handler, once per pass through the loop
        clock.t = i * 0.003
        try:
            _callback_fails()
        except AssertionError:
            lg.error("Exception in callback SerialTransport._write_ready()", exc_info=True)
    text = out.getvalue()
    assert text.count("Traceback") == 1
    # 30 s of flood: the first logged, the rest held within the window
    assert repeats.held_total == 9_999
    clock.t = 61.0
    try:
        _callback_fails()
    except AssertionError:
        lg.error("Exception in callback SerialTransport._write_ready()", exc_info=True)
    last = out.getvalue().strip().splitlines()[-1]
    assert "(repeated 9999 times in the last 61 s, not logged)" in last
    assert "AssertionError: Write buffer should not be empty" in last
    assert out.getvalue().count("Traceback") == 1  # the summary is one line
    assert len(out.getvalue()) < 2_000


def test_messages_with_other_arguments_count_as_repeats_and_others_pass():
    clock = Clock()
    repeats = RepeatFilter(window_s=60, clock=clock)
    lg, out = _logger(repeats)
    for i in range(500):
        lg.warning("serial: line outside a run ignored: %r", f"N{i} G01")
        lg.info("capture: hit %d journaled", i) if i < 1 else None
    lg.warning("OPC UA temperature node %s unreadable", "ns=2;s=/T1")
    lines = out.getvalue().splitlines()
    assert len(lines) == 3, lines
    assert repeats.flush(lg) == 1
    summary = out.getvalue().splitlines()[-1]
    assert "repeated 499 more times" in summary and "line outside a run ignored" in summary
    assert repeats.flush(lg) == 0  # said once


def test_one_template_with_other_words_is_not_a_repeat():
    # a run's phases share the session's template: each is logged
    repeats = RepeatFilter(window_s=60, clock=Clock())
    lg, out = _logger(repeats)
    phases = ["PREPARE", "CAPTURE", "IDENTIFY", "JUDGE", "WRITE-BACK", "IDLE"]
    for phase in phases:
        lg.info("%s %s %s%s", "mill1", "20261128T223755Z-d62f88eeafbb", phase, "")
    assert [ln.split()[-1] for ln in out.getvalue().splitlines()] == phases
    assert repeats.held_total == 0


def test_the_filter_remembers_a_bounded_number_of_messages():
    repeats = RepeatFilter(window_s=60, max_keys=100)
    lg, out = _logger(repeats)
    for i in range(5_000):
        lg.warning(f"distinct message {_word(i)}")  # every one differs in its words
    assert len(repeats._seen) == 100
    assert out.getvalue().count("\n") == 5_000


def test_rumba_run_log_file_rotates_at_its_size(tmp_path):
    # A daemon logging without pause (every line different, so none is held back) keeps at
    # most 1 + 5 files of --log-max-mb each.
    log_file = tmp_path / "daemon.log"
    script = textwrap.dedent(f"""
        import logging
        from pathlib import Path
        from daemon.service.logs import setup_logging
        setup_logging(logging.INFO, Path({str(log_file)!r}), max_bytes=20_000)
        lg = logging.getLogger("rumba.flood")
        for i in range(20_000):
            word = "".join(chr(97 + int(d)) for d in str(i))  # 12 -> "bc": other words
            lg.warning(f"distinct {{word}} " + "x" * 40)
    """)
    subprocess.run([sys.executable, "-c", script], cwd=ROOT, check=True, timeout=120)
    files = sorted(tmp_path.glob("daemon.log*"))
    assert [f.name for f in files] == ["daemon.log", *(f"daemon.log.{i}" for i in range(1, 6))]
    assert all(f.stat().st_size <= 20_000 + 200 for f in files)
    assert "distinct bjjjj" in log_file.read_text()


def test_rumba_run_takes_log_file_and_refuses_a_silly_size(tmp_path):
    from daemon.cli.main import main

    code = main(["run", "--config", "x.yaml", "--log-file", str(tmp_path / "d.log"),
                 "--log-max-mb", "0"])
    assert code == 2
