"""Session state machine: full run, refusal, abort, faults, journal completeness, write-back.

Uses the ReplayLink (daemon/analysis/replay_link.py) that replays exact synthetic probing logs;
the real transports against the simulator are the end-to-end suite's job.
"""

from __future__ import annotations

import asyncio

import pytest

from benchmarks.rigs.daemon_helpers import thesis_rows, thesis_setup
from daemon.analysis.replay_link import Faults, ReplayLink, prepare_from_rows
from daemon.run.session import Refused, Session, State
from daemon.store import baselines
from daemon.store.journal import Store
from tests.waiting import until


@pytest.fixture
def env(tmp_path):
    setup = thesis_setup()
    rows = thesis_rows(setup)
    store = Store(tmp_path / "j.sqlite")
    yield setup, rows, store, tmp_path
    store.close()


def make(env, faults=None, delay_s=0.0, **kw):
    setup, rows, store, tmp = env
    link = ReplayLink(rows, setup.machine, delay_s=delay_s, faults=faults or Faults())
    s = Session(kw.pop("setup", setup), link, store, tmp / "reports",
                prepare=prepare_from_rows(rows), **kw)
    return s, link


def record_states(session: Session) -> list[str]:
    """Every state the session enters, in order (listeners see every change)."""
    out: list[str] = []

    def on(st: dict) -> None:
        if not out or out[-1] != st["state"]:
            out.append(st["state"])

    session.listeners.append(on)
    return out


async def test_full_run_walks_every_state_journals_and_writes_back(env):
    _setup, rows, store, _tmp = env
    s, link = make(env)
    states = record_states(s)
    run_id = s.start("hmi")
    final = await s.wait()
    # the verdict goes back to the CNC before the report is rendered (report_job)
    assert states == ["PREPARE", "STREAM", "CAPTURE", "IDENTIFY", "JUDGE", "WRITE-BACK",
                      "IDLE"]
    assert final["state"] == "IDLE" and final["done"] == final["total"] == len(rows)
    run = store.run(run_id)
    assert run.state == "DONE" and run.hits == len(rows) and run.verdict == "PASS"
    assert [h.seq for h in store.hits(run_id)] == [r.seq for r in rows]
    assert store.verdict(run_id)["written_back"]
    assert [v.status for v in link.verdicts] == ["PASS"] and link.verdicts[0].run_id == run_id
    html, js = store.report(run_id)
    assert html.is_file() and js.is_file()
    # the identified link errors are the injected ones (Table B.2) within 3 u
    links = store.analysis(run_id).links
    assert abs(links["EX0C"].value + 106.0) < 3 * links["EX0C"].std + 0.5


async def test_second_trigger_during_run_is_refused_with_reason(env):
    s, _ = make(env, delay_s=0.002)
    run_id = s.start("cnc")
    await until(lambda: s.done >= 1, 30, "the run's first hit")
    with pytest.raises(Refused, match=rf"run {run_id} in progress .*started by cnc.*hmi"):
        s.start("hmi")
    assert s.run_id == run_id and s.trigger == "cnc"  # the running run is untouched
    await s.abort("hmi")


@pytest.mark.parametrize("source", ["hmi", "can", "cli", "cnc"])
async def test_abort_from_any_source_stops_controller_and_keeps_hits(env, source):
    _setup, _rows, store, _ = env
    s, link = make(env, delay_s=0.02)
    run_id = s.start("hmi")
    while s.done < 10:
        await asyncio.sleep(0.005)
    assert await s.abort(source)
    assert s.state == State.ABORTED and s.reason == f"aborted by {source} during CAPTURE"
    assert link.aborted == 1
    run = store.run(run_id)
    assert run.state == "ABORTED" and run.hits == s.done >= 10
    assert link.verdicts[-1].status == "ERROR"
    assert not await s.abort(source)  # nothing left to abort


async def test_probe_miss_fails_run_journals_the_miss_and_next_run_succeeds(env):
    _setup, _rows, store, _ = env
    s, link = make(env, faults=Faults(no_trigger_at=23))
    run_id = s.start("cnc")
    await s.wait()
    assert s.state == State.FAILED
    assert "did not trigger at touch 23" in s.reason and "ball" in s.reason
    hits = store.hits(run_id)
    assert len(hits) == 23 and not hits[-1].triggered and all(h.triggered for h in hits[:-1])
    assert link.aborted == 1 and link.verdicts[-1].status == "ERROR"
    link.faults = Faults()
    second = s.start("cnc")
    await s.wait()
    assert s.state == State.IDLE and store.run(second).verdict == "PASS"


async def test_lost_link_is_interrupted_and_reconnects_before_next_run(env):
    s, link = make(env, faults=Faults(link_error_at=40))
    link_shown = []
    s.listeners.append(lambda st: link_shown.append(st["link_ok"]))
    s.start("hmi")
    await s.wait()
    assert s.state == State.INTERRUPTED and "connection reset" in s.reason and not s.link_ok
    assert s.reason.endswith("(during CAPTURE)"), s.reason
    assert (link.closed, link.connects) == (0, 0)
    link.faults = Faults()
    s.start("hmi")
    await s.wait()
    assert (link.closed, link.connects) == (1, 1) and s.state == State.IDLE and s.link_ok
    assert link_shown[link_shown.index(False):].count(True) > 0  # shown down, then up again


async def test_silent_controller_times_out_as_an_interrupted_run(env):
    setup = thesis_setup(touch_timeout_s=0.2)
    s, link = make(env, faults=Faults(hang_at=5), setup=setup)
    s.start("hmi")
    await s.wait()
    # rumba lost the run (a RESET plain DNC cannot see, a cut cable): INTERRUPTED, not FAILED
    assert s.state == State.INTERRUPTED and "no probe result for 0.2 s after touch 4" in s.reason
    assert link.aborted == 1


async def test_hit_not_matching_program_fails(env):
    s, _ = make(env, faults=Faults(wrong_identity_at=7))
    s.start("hmi")
    await s.wait()
    assert s.state == State.FAILED and "touch seq 7 reported as" in s.reason


async def test_program_ending_early_fails(env):
    s, _ = make(env, faults=Faults(stop_after=50))
    run_id = s.start("hmi")
    await s.wait()
    assert s.state == State.FAILED and "after 50 of 140 touches" in s.reason
    assert env[2].run(run_id).hits == 50


async def test_fail_verdict_and_drift_against_the_baseline(env):
    setup, _rows, store, _tmp = env
    s, link = make(env)
    first = s.start("hmi")
    await s.wait()
    assert store.run(first).verdict == "PASS"
    assert any(r.startswith("drift not checked: no baseline") for r in s.verdict["reasons"])
    baselines.confirm(store, setup.name, first, "Anna Berg")  # a person accepts it
    # the machine drifts: EB0C +26 → +56 µrad (drift 30 > drift_fail 20, |value| > warn 40)
    drifted = dict(__import__("simulators.exact_log", fromlist=["x"]).THESIS_LINKS_UM_URAD,
                   EB0C=56.0)
    link.rows = thesis_rows(setup, drifted, seed=1)
    s._prepare = prepare_from_rows(link.rows)
    second = s.start("hmi")
    await s.wait()
    v = store.verdict(second)
    assert v["status"] == "FAIL" and link.verdicts[-1].status == "FAIL"
    assert any(r.startswith("EB0C drift") for r in v["reasons"])
    assert store.analysis(second).reference_run == first
    assert s.verdict["baseline"]["run_id"] == first and s.verdict["baseline"]["by"] == \
        "Anna Berg"


async def test_disabled_trigger_is_refused(env):
    setup, _rows, _store, _tmp = env
    from dataclasses import replace

    from daemon.machines.setup import TriggersFile
    s, _ = make(env, setup=replace(setup, triggers=TriggersFile(can=False)))
    with pytest.raises(Refused, match="trigger 'can' is disabled"):
        s.start("can")


async def test_waiting_on_a_stalled_run_can_itself_be_cancelled(env):
    """A caller waiting on the run (the service's CNC trigger) must stop when it is cancelled
    (service shutdown): the wait used to swallow the caller's own cancellation and hang."""
    s, _link = make(env, faults=Faults(hang_at=3))
    stalled = asyncio.Event()  # two hits in: the controller is now silent before seq 3
    s.listeners.append(lambda st: stalled.set() if st["done"] >= 2 or st["state"] in
                       ("IDLE", "FAILED", "ABORTED", "INTERRUPTED") else None)
    s.start("cnc")
    await stalled.wait()
    assert s.status()["state"] == "CAPTURE", s.status()
    waiter = asyncio.ensure_future(s.wait())
    started, _ = await asyncio.wait({waiter}, timeout=0.05)  # the waiter is now inside wait()
    assert not started
    waiter.cancel()
    done, _ = await asyncio.wait({waiter}, timeout=5)
    assert done, "s.wait() swallowed its caller's cancellation"
    assert waiter.cancelled()
    assert await s.abort("test")
