"""The simulated CNC dies (SIGKILL) or hangs (SIGSTOP) while ``rumba verify`` captures over OPC
UA: the run ends INTERRUPTED with a reason that names what happened ("connection to the
controller closed" or, for a hung one, "no answer from the controller within 2 s"), never an
empty one, and the terminal shows no library traceback (asyncua logged one per reconnect
attempt: "Publish iteration crashed; retrying in 1s")."""

from __future__ import annotations

import contextlib
import re
import signal

import pytest
from asyncua import ua

from benchmarks.rigs.daemon_helpers import CONFIG
from drivers.opcua.reasons import why
from tests.cli_helpers import free_port
from tests.stop_helpers import latest_run, rumba_process, until_capturing, write_config

WAIT_S = 120.0


def _sim():
    port = free_port()
    proc = rumba_process("sim", "--machine", str(CONFIG / "machines/thesis_wcbxfzyt.yaml"),
                         "--artefact", str(CONFIG / "artefacts/thesis_4ball.yaml"),
                         "--serve", "opcua", "--security", "none", "--port", str(port),
                         "--time-scale", "0.1")
    for line in proc.stdout:  # type: ignore[union-attr]
        if "listening" in line:
            return proc, line.split("listening:", 1)[1].strip()
    raise AssertionError(f"simulator ended: {proc.stderr.read()}")  # type: ignore[union-attr]


@pytest.mark.parametrize(("how", "said"), [
    (signal.SIGKILL, ("connection to the controller closed",)),
    # hung: a read times out, or asyncua's watchdog closes the silent connection first
    (signal.SIGSTOP, ("no answer from the controller within 2 s",
                      "connection to the controller closed"))])
def test_a_cnc_that_dies_mid_run_is_named_without_a_traceback(tmp_path, how, said):
    sim, url = _sim()
    try:
        cfg = write_config(tmp_path, {"transport": "opcua", "url": url, "security": "none",
                                      "request_timeout_s": 2, "connect_timeout_s": 4})
        proc = rumba_process("verify", "--config", str(cfg), "--machine", "mill1", "--quiet")
        run_id = until_capturing(proc, tmp_path / "journal.sqlite")
        sim.send_signal(how)
        _out, err = proc.communicate(timeout=WAIT_S)
    finally:
        with contextlib.suppress(ProcessLookupError):
            sim.kill()
        sim.wait(30)
    rid, state, reason, hits = latest_run(tmp_path / "journal.sqlite")  # type: ignore[misc]
    assert (rid, state, proc.returncode) == (run_id, "INTERRUPTED", 2), (reason, err)
    assert hits >= 1
    assert any(w in reason for w in said) and "(during CAPTURE)" in reason, reason
    assert not re.search(r":\s*(\(|;|$)", reason), reason  # no cause left empty
    assert "Traceback" not in err and "Publish iteration crashed" not in err, err
    assert any(w in " ".join(err.split()) for w in said), err


@pytest.mark.parametrize(("exc", "words"), [
    (TimeoutError(), "no answer from the controller within 2 s"),
    (ConnectionError(), "connection to the controller closed (ConnectionError)"),
    (ConnectionResetError(104, "Connection reset by peer"),
     "connection to the controller closed ([Errno 104] Connection reset by peer)"),
    (ua.UaStatusCodeError(ua.StatusCodes.BadSessionClosed),
     "connection to the controller closed (BadSessionClosed)"),
    (ua.UaStatusCodeError(ua.StatusCodes.BadNodeIdUnknown), "BadNodeIdUnknown"),
    (ValueError(), "ValueError")])
def test_a_failed_request_is_never_an_empty_reason(exc, words):
    # a bare TimeoutError() has no text: "read touch_counter, state, alarm:  (during CAPTURE)"
    assert why(exc, 2.0) == words
