"""A drift baseline that cannot lie: `rumba baseline set` and the HMI refuse a run that FAILed,
predates a compensation written to the controller, or was identified against a model the
controller no longer runs — unless a person overrides it with a reason, journaled with the
objections; the verification run of a compensation is proposed only when it did not FAIL; on
the page the button says why before anyone clicks (an operator: disabled, by role)."""

from __future__ import annotations

import time

import pytest

from benchmarks.rigs.daemon_helpers import thesis_rows, thesis_setup, write_daemon_yaml
from benchmarks.rigs.report_helpers import journal_run
from daemon.analysis.replay_link import ReplayLink, prepare_from_rows
from daemon.compensation import journal as cj
from daemon.config import load_daemon_config
from daemon.reports.compensation import verification_of
from daemon.service.service import Service
from daemon.store import baselines
from daemon.store.journal import Store
from tests.browser import chromium
from tests.cli_helpers import run_cli
from tests.test_hmi_users import PASSWORDS, TOKEN, add_user, jar_session, sign_in


@pytest.fixture
def world(tmp_path):
    """daemon.yaml for mill1 and its journal with runs R0, R1, R2 an hour apart (DONE)."""
    cfg = write_daemon_yaml(tmp_path)
    setup = load_daemon_config(cfg).machines["mill1"]
    store = Store(tmp_path / "journal.sqlite")
    now = time.time()
    for i in range(3):
        journal_run(store, setup, f"R{i}", i, now - (3 - i) * 3600)
    yield str(cfg), store
    store.close()


def _fail(store: Store, run_id: str) -> None:
    store.save_verdict(run_id, "FAIL", ["EX0C -105.8 µm outside ±50 µm"], [], "FAIL")


def _compensation(store: Store, after: str, source: str = "R0") -> int:
    """An applied compensation written a minute after run ``after`` started."""
    return cj.record(store, "mill1", source, "siemens", "applied",
                     [cj.ValueChange("c-x", "$TC_CARR15[1]", "mm", 0.0, 0.1, 0.1)],
                     confirmed_by="Anna Berg", applied_at=store.run(after).started_at + 60)


def test_a_failed_run_is_refused_unless_overridden_with_a_reason(world, capsys):
    cfg, store = world
    _fail(store, "R1")
    code, out, err = run_cli(["baseline", "set", "mill1", "R1", "--config", cfg, "--by",
                              "Jo Keller"], capsys)
    assert code == 2 and out.count("\n") == 1, (out, err)
    assert "refused: run R1 is not made the drift baseline: it FAILed (EX0C -105.8 µm" in out
    assert "--override REASON" in out
    assert baselines.current(store, "mill1") is None  # nothing journaled
    code, _, err = run_cli(["baseline", "set", "mill1", "R1", "--config", cfg, "--by", "Jo",
                            "--override", "  "], capsys)
    assert code == 2 and "--override: give the reason" in err
    code, out, err = run_cli(["baseline", "set", "mill1", "R1", "--config", cfg, "--by",
                              "Jo Keller", "--override", "FAIL is the accepted state until "
                              "the spindle is replaced"], capsys)
    assert code == 0, err
    b = baselines.current(store, "mill1")
    assert b.run_id == "R1" and b.by == "Jo Keller"
    assert b.note.startswith("[OVERRIDE by Jo Keller: FAIL is the accepted state until the "
                             "spindle is replaced]") and "it FAILed (EX0C" in b.note
    code, out, _ = run_cli(["baseline", "show", "mill1", "--config", cfg], capsys)
    assert "warning: this baseline is questionable: it FAILed" in out and "OVERRIDE" in out
    # a PASS run needs no override
    code, out, err = run_cli(["baseline", "set", "mill1", "R2", "--config", cfg, "--by", "Jo"],
                             capsys)
    assert code == 0, err
    assert baselines.current(store, "mill1").note == ""


def test_a_run_before_a_compensation_is_refused(world, capsys):
    cfg, store = world
    row = _compensation(store, after="R1")
    code, out, _ = run_cli(["baseline", "set", "mill1", "R1", "--config", cfg, "--by", "Jo"],
                           capsys)
    assert code == 2 and f"before compensation #{row} (written " in out, out
    assert "by Anna Berg): its links were identified against a controller model the " \
           "controller no longer runs" in out
    assert baselines.current(store, "mill1") is None
    # the run after it is the machine as it is
    assert run_cli(["baseline", "set", "mill1", "R2", "--config", cfg, "--by", "Jo"],
                   capsys)[0] == 0
    # rolled back: the model is the run's again, but the run still predates a write
    cj.update(store, row, state="rolled_back")
    cj.record(store, "mill1", "R0", "siemens", "rolled_back",
              [cj.ValueChange("c-x", "$TC_CARR15[1]", "mm", 0.1, 0.0, -0.1)],
              confirmed_by="Anna Berg", reason=f"{cj.ROLLBACK_PREFIX}{row}",
              applied_at=store.run("R2").started_at - 30)
    code, out, _ = run_cli(["baseline", "set", "mill1", "R0", "--config", cfg, "--by", "Jo"],
                           capsys)
    assert code == 2 and f"before compensation #{row}" in out and "since rolled back" in out, out


def test_a_failed_verification_run_is_not_proposed(world):
    _cfg, store = world
    _compensation(store, after="R1", source="R1")
    _fail(store, "R2")
    assert verification_of(store, store.run("R2"), store.analysis("R2")) is not None
    assert baselines.pending(store, "mill1") is None  # FAILed: never proposed
    assert cj.last_applied(store, "mill1").verify_run_id == "R2"  # still its verification


async def _service(tmp_path, capsys, monkeypatch) -> Service:
    """The daemon with accounts olga (operator) and erik (engineer) and limits the thesis
    machine's EX0C −106 µm FAILs."""
    users = tmp_path / "users"
    add_user(capsys, monkeypatch, users, "olga", "operator", PASSWORDS["olga"])
    add_user(capsys, monkeypatch, users, "erik", "engineer", PASSWORDS["erik"])
    cfg = write_daemon_yaml(tmp_path, token=TOKEN)
    text = cfg.read_text().replace(f"token: {TOKEN}}}", f"token: {TOKEN}, users_file: users}}")
    cfg.write_text(text.replace("default_translation_um: {warn: 150, fail: 300}",
                                "default_translation_um: {warn: 25, fail: 50}"))
    rows = thesis_rows(thesis_setup())
    svc = Service(load_daemon_config(cfg), lambda s: ReplayLink(rows, s.machine),
                  prepare=prepare_from_rows(rows))
    await svc.start()
    return svc


async def test_hmi_api_refuses_with_the_objections_and_journals_an_override(
        tmp_path, capsys, monkeypatch):
    svc = await _service(tmp_path, capsys, monkeypatch)
    url = svc.hmi_url + "api/machines/mill1/baseline"
    try:
        run_id = svc.sessions["mill1"].start("cli")
        await svc.sessions["mill1"].wait()
        assert svc.store.run(run_id).verdict == "FAIL"
        async with jar_session() as erik:
            _, csrf = await sign_in(erik, svc.hmi_url, "erik", PASSWORDS["erik"])
            h = {"X-CSRF-Token": csrf}
            got = await (await erik.get(url, params={"run_id": run_id})).json()
            assert got["objections"] and got["objections"][0].startswith("it FAILed ("), got
            r = await erik.post(url, headers=h, json={"run_id": run_id})
            body = await r.json()
            assert r.status == 409 and body["objections"] == got["objections"], body
            assert baselines.current(svc.store, "mill1") is None
            r = await erik.post(url, headers=h, json={"run_id": run_id, "override": "x"})
            assert r.status == 422 and "override: give the reason" in await r.text()
            r = await erik.post(url, headers=h, json={"run_id": run_id,
                                                      "override": "known FAIL, drift watch"})
            assert r.status == 200, await r.text()
            b = baselines.current(svc.store, "mill1")
            assert b.by == "erik" and "[OVERRIDE by erik: known FAIL, drift watch]" in b.note
            assert (await r.json())["questionable"] == got["objections"]
    finally:
        await svc.stop()


@pytest.mark.peer
async def test_browser_the_button_says_why_before_a_click(tmp_path, capsys, monkeypatch):
    """Chromium: signed in as an operator the button is there, disabled, naming the role; as
    an engineer on a FAILed run it is disabled naming the objection, and Override… asks for
    the reason and journals it."""
    svc = await _service(tmp_path, capsys, monkeypatch)
    try:
        run_id = svc.sessions["mill1"].start("cli")
        await svc.sessions["mill1"].wait()
        card = "document.querySelector('.machine')"
        btn, over = f"{card}.querySelector('.set-baseline')", \
            f"{card}.querySelector('.set-baseline-override')"
        why = f"{card}.querySelector('.set-baseline-why').textContent"
        async with chromium(tmp_path / "olga") as cdp:
            sid = await cdp.page()
            await cdp.sign_in_user(sid, svc.hmi_url, "olga", PASSWORDS["olga"])
            await cdp.wait_for(sid, f"!!{btn} && !{btn}.hidden")
            assert await cdp.eval(sid, f"{btn}.disabled") and await cdp.eval(sid, f"{over}.hidden")
            assert await cdp.eval(sid, why) == ("Signed in as olga (operator): an engineer or "
                                                "admin sets the baseline.")
        async with chromium(tmp_path / "erik") as cdp:
            sid = await cdp.page()
            await cdp.sign_in_user(sid, svc.hmi_url, "erik", PASSWORDS["erik"])
            await cdp.wait_for(sid, f"!!{btn} && !{btn}.hidden && !{over}.hidden")
            assert await cdp.eval(sid, f"{btn}.disabled")
            text = await cdp.eval(sid, why)
            assert text.startswith("Not a baseline without an override: it FAILed ("), text
            await cdp.screenshot(sid, tmp_path / "hmi-baseline-objection.png")
            await cdp.eval(sid, "window.prompt = () => 'FAIL known, watching drift'; true")
            await cdp.eval(sid, f"{over}.click(); true")
            await cdp.wait_for(sid, f"{card}.querySelector('.message').textContent"
                                    ".startsWith('Baseline now: run ')")
        b = baselines.current(svc.store, "mill1")
        assert (b.run_id, b.by) == (run_id, "erik")
        assert b.note.startswith("[OVERRIDE by erik: FAIL known, watching drift]")
    finally:
        await svc.stop()
