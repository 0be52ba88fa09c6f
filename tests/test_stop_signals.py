"""Ctrl-C and SIGTERM on a real ``rumba verify`` process (issue 20, item 6): the simulated CNC
is its own process (``rumba sim --serve opcua``), ``rumba verify`` another; the signal arrives
while the run captures (seen in the journal: the first hits are in). Each row checks the exit
code (130 SIGINT, 143 SIGTERM), no traceback on stderr, the journal row ABORTED naming the
signal and the phase, and a second ``rumba verify`` against the same simulator process reaching
its verdict (its program was accepted: the first one was reset and unloaded)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.cli_helpers import free_port
from tests.daemon_helpers import CONFIG
from tests.stop_helpers import latest_run, write_config

ROOT = Path(__file__).resolve().parents[1]
WAIT_S = 120.0  # a safety net for a loaded computer; every wait ends on an event before


def _rumba(*argv: str, **kw) -> subprocess.Popen:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    env.pop("RUMBA_DEBUG", None)
    return subprocess.Popen([sys.executable, "-m", "daemon.cli", *argv], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)


@pytest.fixture(scope="module")
def sim_url():
    """One simulator process for the module, slow enough to be caught probing whatever the
    load: at time scale 0.1 the 140 touches take ≈ 11 s, so a signal sent within seconds of the
    first journaled hit lands in CAPTURE (at 0.02, ≈ 2 s, a loaded machine saw the run reach
    IDENTIFY first)."""
    port = free_port()
    proc = _rumba("sim", "--machine", str(CONFIG / "machines/thesis_wcbxfzyt.yaml"),
                  "--artefact", str(CONFIG / "artefacts/thesis_4ball.yaml"),
                  "--serve", "opcua", "--security", "none", "--port", str(port),
                  "--time-scale", "0.1")
    try:
        deadline = time.monotonic() + WAIT_S
        for line in proc.stdout:  # type: ignore[union-attr]
            if "listening" in line:
                yield line.split("listening:", 1)[1].strip()
                break
            if time.monotonic() > deadline:
                raise AssertionError("simulator did not start")
        else:
            raise AssertionError(f"simulator ended: {proc.stderr.read()}")  # type: ignore
    finally:
        proc.terminate()
        proc.wait(10)


def _journal_row(db: Path) -> tuple[str, str, int] | None:
    """(state, reason, hits) of the latest run."""
    row = latest_run(db)
    return None if row is None else row[1:]


@pytest.mark.parametrize(("sig", "code", "name"), [
    (signal.SIGINT, 130, "Ctrl-C (SIGINT)"), (signal.SIGTERM, 143, "SIGTERM")])
def test_signal_on_rumba_verify_aborts_resets_and_the_next_run_passes(
        sim_url, tmp_path, sig, code, name):
    cfg = write_config(tmp_path, {"transport": "opcua", "url": sim_url, "security": "none"})
    db = tmp_path / "journal.sqlite"
    proc = _rumba("verify", "--config", str(cfg), "--machine", "mill1", "--quiet")
    deadline = time.monotonic() + WAIT_S
    while True:  # the journal is the event: hits are in, the run is capturing
        row = _journal_row(db)
        if row and row[2] >= 1:
            break
        if proc.poll() is not None:
            raise AssertionError(f"verify ended ({proc.returncode}) before capturing: "
                                 f"{proc.stderr.read()}")  # type: ignore[union-attr]
        assert time.monotonic() < deadline, "no hit journaled"
        time.sleep(0.05)
    proc.send_signal(sig)
    _out, err = proc.communicate(timeout=WAIT_S)
    assert proc.returncode == code, err
    assert "Traceback" not in err and "ProgrammingError" not in err, err
    state, reason, _ = _journal_row(db)  # type: ignore[misc]
    assert state == "ABORTED" and reason.startswith(f"aborted by {name} during "), reason
    assert reason.split(" during ")[1].split(";")[0] in ("STREAM", "CAPTURE"), reason
    assert f"ABORTED: aborted by {name}" in err or "ABORTED" in err, err
    again = _rumba("verify", "--config", str(cfg), "--machine", "mill1", "--quiet")
    out2, err2 = again.communicate(timeout=WAIT_S * 3)
    assert again.returncode in (0, 1), err2  # a verdict (PASS/WARN or FAIL), not an error
    assert "Traceback" not in err2 and "report:" in out2, err2
    assert _journal_row(db)[0] == "DONE"  # type: ignore[index]
