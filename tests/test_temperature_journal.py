"""Temperature readings are journaled like hits: each in its own transaction
on arrival, so a daemon SIGKILLed mid-run loses none it had recorded; numbered in arrival
order per run, an unreadable channel kept with its reason."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from contracts.temperatures import TemperatureReading
from daemon.store.journal import Store
from daemon.store.temperatures import journal_temperature, temperatures

_WRITER = """
import sys
from contracts.temperatures import TemperatureReading
from daemon.store.journal import Store
from daemon.store.temperatures import journal_temperature
from tests.store_helpers import hit
s = Store(sys.argv[1], synchronous=sys.argv[2])
s.new_run("K", "mill1", "cnc")
for k in range(1, 100000):
    s.journal_hit("K", hit(k))
    journal_temperature(s, "K", TemperatureReading("spindle", "pose", k, float(k), 20 + k / 1e4))
    print(k, flush=True)  # reported only after both commits returned
"""


@pytest.mark.parametrize("sync", ["FULL", "NORMAL"])
def test_kill_9_loses_no_committed_reading(tmp_path, sync):
    db = tmp_path / "j.sqlite"
    p = subprocess.Popen([sys.executable, "-c", _WRITER, str(db), sync],
                         stdout=subprocess.PIPE, text=True, cwd=os.getcwd())
    last = 0
    deadline = time.monotonic() + 30
    while last < 100 and time.monotonic() < deadline:
        line = p.stdout.readline()
        if not line:
            break
        last = int(line)
    os.kill(p.pid, signal.SIGKILL)
    p.wait()
    p.stdout.close()
    assert last >= 100, "the writer did not get going"
    s = Store(db)
    got = temperatures(s, "K")
    s.close()
    assert len(got) >= last  # every reading it reported, maybe one more
    assert [r.pose for r in got] == list(range(1, len(got) + 1))
    assert got[last - 1] == TemperatureReading("spindle", "pose", last, float(last),
                                               20 + last / 1e4)


def test_readings_keep_arrival_order_and_the_reason_of_a_failed_read(tmp_path):
    s = Store(tmp_path / "j.sqlite")
    s.new_run("R1", "mill1", "cnc")
    s.new_run("R2", "mill1", "cnc")
    a = TemperatureReading("spindle", "start", None, 0.1, 21.25)
    b = TemperatureReading("column", "start", None, 0.1, None, "modbus-tcp 10.0.0.9:502: "
                                                               "cannot connect")
    c = TemperatureReading("spindle", "pose", 0, 5.0, 21.5)
    for r in (a, b, c):
        journal_temperature(s, "R1", r)
    journal_temperature(s, "R2", a)
    assert temperatures(s, "R1") == [a, b, c] and temperatures(s, "R2") == [a]
    s.close()
