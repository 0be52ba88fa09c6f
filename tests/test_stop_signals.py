"""Ctrl-C and SIGTERM on a real ``rumba verify`` process: the simulated CNC
is its own process (``rumba sim --serve opcua``), ``rumba verify`` another; the signal arrives
while the run captures (seen in the journal: the first hits are in). Each row checks the exit
code (130 SIGINT, 143 SIGTERM), no traceback on stderr, the journal row ABORTED naming the
signal and the phase, and a second ``rumba verify`` against the same simulator process reaching
its verdict (its program was accepted: the first one was reset and unloaded). Then the same
against a real ``rumba run`` daemon: a signal on ``rumba verify --daemon`` aborts the daemon's
run (HMI API, same bearer token) and exits once the daemon reports it ended, the daemon serving
on; SIGTERM on the daemon ends its run INTERRUPTED and, restarted with ``rerun_interrupted``,
it runs the machine again."""

from __future__ import annotations

import json
import signal
import subprocess
import time
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml

from benchmarks.rigs.daemon_helpers import CONFIG
from tests.cli_helpers import free_port
from tests.stop_helpers import latest_run, rumba_process, until_capturing, write_config

ROOT = Path(__file__).resolve().parents[1]
WAIT_S = 120.0  # a safety net for a loaded computer; every wait ends on an event before


@pytest.fixture(scope="module")
def sim_url():
    """One simulator process for the module, slow enough to be caught probing whatever the
    load: at time scale 0.1 the 140 touches take ≈ 11 s, so a signal sent within seconds of the
    first journaled hit lands in CAPTURE (at 0.02, ≈ 2 s, a loaded machine saw the run reach
    IDENTIFY first)."""
    port = free_port()
    proc = rumba_process("sim", "--machine", str(CONFIG / "machines/thesis_wcbxfzyt.yaml"),
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
    proc = rumba_process("verify", "--config", str(cfg), "--machine", "mill1", "--quiet")
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
    again = rumba_process("verify", "--config", str(cfg), "--machine", "mill1", "--quiet")
    out2, err2 = again.communicate(timeout=WAIT_S * 3)
    assert again.returncode in (0, 1), err2  # a verdict (PASS/WARN or FAIL), not an error
    assert "Traceback" not in err2 and "report:" in out2, err2
    assert _journal_row(db)[0] == "DONE"  # type: ignore[index]


# ------------------------------------------------------------------ `rumba verify --daemon`
TOKEN = "t0k3n-for-tests-0123456789"  # tests.stop_helpers.write_config's HMI token


@dataclass
class Daemon:
    """A ``rumba run`` process with its HMI on a loopback port (its log in a file: a pipe
    nobody reads would stall it)."""

    cfg: Path
    db: Path
    log: Path
    port: int
    proc: subprocess.Popen | None = None

    def start(self) -> None:
        with open(self.log, "a") as fh:
            self.proc = rumba_process("run", "--config", str(self.cfg), stdout=fh,
                                      stderr=subprocess.STDOUT)
        deadline = time.monotonic() + WAIT_S
        while "rumba: HMI at" not in self.log.read_text():
            assert self.proc.poll() is None, f"rumba run ended: {self.log.read_text()}"
            assert time.monotonic() < deadline, self.log.read_text()
            time.sleep(0.05)

    def status(self) -> dict:
        req = urllib.request.Request(f"http://127.0.0.1:{self.port}/api/status",
                                     headers={"Authorization": f"Bearer {TOKEN}"})
        with urllib.request.urlopen(req, timeout=30) as r:
            return json.load(r)["mill1"]

    def stop(self) -> int:
        assert self.proc is not None
        self.proc.send_signal(signal.SIGTERM)
        return self.proc.wait(WAIT_S)


def _serving(sim_url: str, tmp: Path) -> Iterator[Daemon]:
    port = free_port()
    cfg = write_config(tmp, {"transport": "opcua", "url": sim_url, "security": "none"},
                       hmi_port=port)
    d = Daemon(cfg, tmp / "journal.sqlite", tmp / "daemon.log", port)
    d.start()
    try:
        yield d
    finally:
        if d.proc is not None and d.proc.poll() is None:
            d.stop()


@pytest.fixture(scope="module")
def daemon(sim_url, tmp_path_factory):
    """One daemon serving the tests that leave it serving, in whatever order they run."""
    yield from _serving(sim_url, tmp_path_factory.mktemp("daemon"))


@pytest.fixture
def own_daemon(sim_url, tmp_path):
    """A daemon of the test's own, for a test that stops it and changes its configuration."""
    yield from _serving(sim_url, tmp_path)


def _verify_daemon(d: Daemon) -> subprocess.Popen:
    return rumba_process("verify", "--config", str(d.cfg), "--machine", "mill1", "--daemon",
                         "--quiet")


@pytest.mark.parametrize(("sig", "code", "name"), [
    (signal.SIGINT, 130, "Ctrl-C (SIGINT)"), (signal.SIGTERM, 143, "SIGTERM")])
def test_signal_on_rumba_verify_daemon_aborts_the_daemons_run(daemon, sig, code, name):
    """The signal aborts the run on the daemon (HMI API, the same bearer token); verify exits
    once the daemon reports the run ended; the daemon serves on, ready for the next run."""
    before = latest_run(daemon.db)
    proc = _verify_daemon(daemon)
    run_id = until_capturing(proc, daemon.db, not_run=before[0] if before else None)
    proc.send_signal(sig)
    _out, err = proc.communicate(timeout=WAIT_S)
    assert proc.returncode == code, err
    assert "Traceback" not in err and "internal error" not in err, err
    rid, state, reason, _ = latest_run(daemon.db)  # type: ignore[misc]
    assert (rid, state) == (run_id, "ABORTED"), reason
    assert reason.startswith(f"aborted by {name} on rumba verify --daemon during "), reason
    assert reason.split(" during ")[1].split(";")[0] in ("STREAM", "CAPTURE"), reason
    assert f"run {run_id} ABORTED: aborted by {name}" in " ".join(err.split()), err
    st = daemon.status()  # the run had ended when verify returned: nothing runs there
    assert (st["run_id"], st["state"], st["busy"]) == (run_id, "ABORTED", False), st
    assert daemon.proc is not None and daemon.proc.poll() is None  # the daemon serves on


def test_after_the_aborts_a_run_through_the_daemon_reaches_its_verdict(daemon):
    proc = _verify_daemon(daemon)
    out, err = proc.communicate(timeout=WAIT_S * 3)
    assert proc.returncode in (0, 1), err  # a verdict (PASS/WARN or FAIL), not an error
    assert "Traceback" not in err and "report:" in out, err
    assert latest_run(daemon.db)[1] == "DONE"  # type: ignore[index]


def test_sigterm_on_the_daemon_interrupts_its_run_and_the_restart_reruns_it(own_daemon):
    """The daemon stopping under a run (SIGTERM, as systemd stops it): the run ends
    INTERRUPTED with its phase, the controller reset; ``rumba verify --daemon`` following it
    ends with that state (exit 2, no traceback); started again with ``rerun_interrupted``, the
    daemon runs the machine again and the controller takes the new program."""
    before = latest_run(own_daemon.db)
    proc = _verify_daemon(own_daemon)
    run_id = until_capturing(proc, own_daemon.db, not_run=before[0] if before else None)
    assert own_daemon.stop() == 0, own_daemon.log.read_text()
    _out, err = proc.communicate(timeout=WAIT_S)
    assert proc.returncode == 2 and "Traceback" not in err, err
    rid, state, reason, _ = latest_run(own_daemon.db)  # type: ignore[misc]
    assert (rid, state) == (run_id, "INTERRUPTED"), reason
    assert reason.startswith("interrupted by the daemon stopping during "), reason
    assert "controller abort failed" not in reason, reason  # the reset reached the CNC
    log = own_daemon.log.read_text()
    assert "Traceback" not in log and "rumba: stopped" in log, log
    doc = yaml.safe_load(own_daemon.cfg.read_text())
    doc["machines"][0]["rerun_interrupted"] = True
    own_daemon.cfg.write_text(yaml.safe_dump(doc), encoding="utf-8")
    own_daemon.start()
    rerun = until_capturing(own_daemon.proc, own_daemon.db,  # type: ignore[arg-type]
                            not_run=run_id)
    assert latest_run(own_daemon.db)[0] == rerun  # type: ignore[index]
    assert own_daemon.status()["trigger"] == "rerun"
    assert own_daemon.stop() == 0
    assert latest_run(own_daemon.db)[1] == "INTERRUPTED"  # type: ignore[index]
