"""The drift baseline on a real SQLite journal: a person sets or confirms it
(`rumba baseline set/show`), who and when are journaled, a compensation's verification run is
proposed and changes nothing until confirmed, the judge checks drift against it (not against
"the last PASS run": a machine staying in WARN keeps its drift check), and bad input gets one
line naming what is wrong."""

from __future__ import annotations

import time

import pytest

from benchmarks.rigs.daemon_helpers import write_daemon_yaml
from benchmarks.rigs.report_helpers import journal_run
from daemon.analysis.judge import NO_BASELINE, judge
from daemon.compensation import journal as cj
from daemon.config import load_daemon_config
from daemon.reports.compensation import verification_of
from daemon.store import baselines
from daemon.store.journal import Store
from tests.cli_helpers import run_cli


@pytest.fixture
def world(tmp_path):
    """daemon.yaml for mill1 and its journal with runs R0 (PASS, yesterday) and R1, R2."""
    cfg = write_daemon_yaml(tmp_path)
    setup = load_daemon_config(cfg).machines["mill1"]
    store = Store(tmp_path / "journal.sqlite")
    now = time.time()
    for i in range(3):
        journal_run(store, setup, f"R{i}", i, now - (3 - i) * 3600)
    store.new_run("R9", "mill1", "cnc", started_at=now)  # aborted, no result
    store.set_state("R9", "ABORTED", "aborted by hmi")
    yield str(cfg), setup, store
    store.close()


def test_set_and_show_journal_who_and_when(world, capsys):
    cfg, _setup, store = world
    code, out, _ = run_cli(["baseline", "show", "mill1", "--config", cfg], capsys)
    assert code == 0 and "mill1: baseline none: drift not checked" in out
    code, out, err = run_cli(["baseline", "set", "mill1", "R1", "--config", cfg,
                              "--by", "Anna Berg", "--note", "after the spindle service"],
                             capsys)
    assert code == 0, err
    assert out.startswith("mill1: baseline run R1 of ") and "confirmed by Anna Berg" in out
    b = baselines.current(store, "mill1")
    assert (b.run_id, b.by, b.state, b.note) == ("R1", "Anna Berg", "confirmed",
                                                "after the spindle service")
    assert abs(b.at - time.time()) < 600  # when, journaled (a clock, not a timing assertion)
    run_cli(["baseline", "set", "mill1", "R2", "--config", cfg, "--by", "Jo Keller"], capsys)
    assert [(x.run_id, x.by) for x in baselines.history(store, "mill1")] == [
        ("R2", "Jo Keller"), ("R1", "Anna Berg")]  # every decision kept
    code, out, _ = run_cli(["baseline", "show", "mill1", "--config", cfg], capsys)
    assert "baseline run R2 of " in out and "confirmed by Jo Keller" in out


@pytest.mark.parametrize("argv, message", [
    (["set", "mill1", "R1"], "--by: give a name"),
    (["set", "mill1", "R1", "--by", "unattended"], "reserved"),
    (["set", "mill1", "R1", "--by", "Anna\nBerg"], "not allowed"),
    (["set", "mill1", "NOPE", "--by", "A"], "run NOPE is not in the journal"),
    (["set", "mill1", "R9", "--by", "A"], "run R9 has no result (state ABORTED)"),
    (["set", "mill1", "../x", "--by", "A"], "invalid run id"),
    (["set", "mill2", "R1", "--by", "A"], "machine 'mill2' is not in"),
    (["set", "mill1", "--by", "A"], "no proposed baseline to confirm"),
])
def test_bad_input_is_one_line(world, capsys, argv, message):
    cfg, _setup, store = world
    code, _out, err = run_cli(["baseline", *argv, "--config", cfg], capsys)
    assert code == 2 and message in err and err.count("\n") == 1, err
    assert baselines.current(store, "mill1") is None  # nothing journaled


def test_an_error_verdict_is_no_baseline(world, capsys):
    cfg, _setup, store = world
    store.db.execute("UPDATE runs SET verdict='ERROR' WHERE id='R1'")
    code, _, err = run_cli(["baseline", "set", "mill1", "R1", "--config", cfg, "--by", "A"],
                           capsys)
    assert code == 2 and "verdict is ERROR" in err


def test_the_verification_run_is_proposed_and_a_person_confirms_it(world, capsys):
    cfg, _setup, store = world
    run_cli(["baseline", "set", "mill1", "R0", "--config", cfg, "--by", "Anna Berg"], capsys)
    applied = store.run("R2").started_at - 60
    row = cj.record(store, "mill1", "R1", "siemens", "applied",
                    [cj.ValueChange("c-x", "$TC_CARR15[1]", "mm", 0.0, 0.1, 0.1)],
                    confirmed_by="Anna Berg", applied_at=applied)
    assert verification_of(store, store.run("R2"), store.analysis("R2")) is not None
    wait = baselines.pending(store, "mill1")
    assert (wait.run_id, wait.state, wait.by) == ("R2", "proposed", "rumba")
    assert f"compensation #{row}" in wait.note
    assert baselines.current(store, "mill1").run_id == "R0"  # a proposal changes nothing
    code, out, _ = run_cli(["baseline", "show", "mill1", "--config", cfg], capsys)
    assert "proposed: run R2 of " in out and "rumba baseline set mill1 R2 --by NAME" in out
    code, out, err = run_cli(["baseline", "set", "mill1", "--config", cfg, "--by", "Jo Keller"],
                             capsys)  # no run named: the proposed one
    assert code == 0, err
    assert baselines.current(store, "mill1").run_id == "R2"
    assert baselines.pending(store, "mill1") is None


def test_drift_is_judged_against_the_baseline_not_the_last_pass(world, capsys):
    """A machine that stays in WARN kept no drift check before (no PASS run): with a baseline
    it has one, against the run a person named."""
    cfg, setup, store = world
    store.db.execute("UPDATE runs SET verdict='WARN'")  # no PASS run at all
    assert store.last_good("mill1") is None
    a2 = store.analysis("R2")
    j = judge(a2, setup.tolerances, None)
    assert not [c for c in j.checks if c.reference is not None]
    assert any(r.startswith(NO_BASELINE) for r in j.reasons)
    run_cli(["baseline", "set", "mill1", "R0", "--config", cfg, "--by", "Anna Berg"], capsys)
    ref = baselines.reference(store, "mill1", before="R2")
    assert ref is not None and ref[0].run_id == "R0"
    j = judge(a2, setup.tolerances, ref[1])
    drift = [c for c in j.checks if c.quantity.endswith(" drift")]
    assert drift and {c.reference_run for c in drift} == {"R0"}
    r0 = store.analysis("R0")
    c = next(c for c in drift if c.quantity == "EB0C drift")
    assert c.value == pytest.approx(a2.links["EB0C"].value - r0.links["EB0C"].value)
    assert not any(r.startswith(NO_BASELINE) for r in j.reasons)
    assert baselines.reference(store, "mill1", before="R0") is None  # never itself


async def test_hmi_only_an_engineer_sets_it_and_the_account_names_the_person(
        tmp_path, capsys, monkeypatch):
    """On the HMI with accounts: an operator is refused (403, nothing journaled); an engineer
    sets it and the journal names the account, not a name the page typed; the token (a
    script) must type a person's name; bad input is a 4xx with the reason."""
    from tests.test_hmi_users import PASSWORDS, TOKEN, accounts_service, jar_session, sign_in

    svc = await accounts_service(tmp_path, capsys, monkeypatch)
    url = svc.hmi_url + "api/machines/mill1/baseline"
    try:
        run_id = svc.sessions["mill1"].start("cli")
        await svc.sessions["mill1"].wait()
        assert svc.store.run(run_id).state == "DONE"
        async with jar_session() as olga, jar_session() as erik, \
                jar_session() as script:
            _, csrf = await sign_in(olga, svc.hmi_url, "olga", PASSWORDS["olga"])
            r = await olga.post(url, headers={"X-CSRF-Token": csrf},
                                json={"run_id": run_id, "by": "olga"})
            assert r.status == 403 and "needs an engineer or admin" in await r.text()
            assert baselines.current(svc.store, "mill1") is None
            r = await olga.get(url)  # looking is for everyone
            assert r.status == 200 and (await r.json())["text"] == NO_BASELINE
            _, csrf = await sign_in(erik, svc.hmi_url, "erik", PASSWORDS["erik"])
            r = await erik.post(url, headers={"X-CSRF-Token": csrf},
                                json={"run_id": run_id, "by": "Somebody Else"})
            assert r.status == 200, await r.text()
            b = baselines.current(svc.store, "mill1")
            assert (b.run_id, b.by) == (run_id, "erik") and "engineer via password" in b.note
            bearer = {"Authorization": f"Bearer {TOKEN}"}
            for body, status, why in (
                    ({"run_id": run_id}, 422, "by: give a name"),
                    ({"run_id": "nope", "by": "Anna"}, 409, "run nope is not in the journal"),
                    ({"run_id": 7, "by": "Anna"}, 422, "run_id: a run id"),
                    ({"by": "Anna"}, 409, "no proposed baseline")):
                r = await script.post(url, headers=bearer, json=body)
                assert r.status == status and why in await r.text(), (body, await r.text())
            r = await script.post(svc.hmi_url + "api/machines/mill9/baseline", headers=bearer,
                                  json={"run_id": run_id, "by": "Anna"})
            assert r.status == 404
            assert [x.by for x in baselines.history(svc.store, "mill1")] == ["erik"]
    finally:
        await svc.stop()
