"""A run whose start temperature was not read (found in review): every view shows the same
numbers for it — the run's mean (contracts.temperatures.run_mean_c, one definition for the
report, ``rumba history --against-temperature``, the HMI and the fleet page) and its change —
and none claims a change it did not measure (with only the end read, the summary made the end
its own start: "+0.0 °C", which passed the change limit). The fleet half runs against a real
PostgreSQL fed by the daemon's own drainer."""

from __future__ import annotations

import html
import time

import aiohttp
import pytest

from benchmarks.rigs.daemon_helpers import thesis_rows, thesis_setup, write_daemon_yaml
from benchmarks.rigs.temperature_helpers import fleet_against
from contracts.temperatures import TemperatureReading, channel_text, run_mean_c, summarise
from daemon.analysis.judge import judge
from daemon.analysis.replay_link import ReplayLink, prepare_from_rows
from daemon.analysis.result import Analysis, LinkError
from daemon.analysis.temperature_trend import points
from daemon.cli.main import main as cli_main
from daemon.config import load_daemon_config
from daemon.machines.tolerances import Limit, Tolerances
from daemon.reports.temperatures import audit_text, table_rows, temperature_lines
from daemon.run.temperatures import NOT_PRINTED
from daemon.service.service import Service
from daemon.store.drain import Drainer
from daemon.store.journal import Store
from daemon.store.temperatures import journal_temperature, temperatures
from tests.fleet_helpers import fresh_db, pg

__all__ = ["pg"]  # the module's PostgreSQL (tests/fleet_helpers.py)
CHANNELS = "    temperatures: [{name: spindle, address: /Channel/Temperatures/Z}]"
HMI_TOKEN = "t0k3n-for-run-mean-0123456789"
SOURCES = {"spindle": "spindle: opcua /Channel/Temperatures/Z"}
NO_ANSWER = "no answer in 3 s; not read again until the end of the run"
DOWN = "not read: unreachable since no answer in 3 s at start; tried again at the end of the run"


def readings(kind: str) -> list[TemperatureReading]:
    """One run's spindle readings: ``full``; ``no-start`` (a start that failed at once, the
    poses and the end read); ``end-only`` (the channel silent at the start: unreachable for
    every pose, read again at the end — the case the summary used to fill with the end).
    Printed over DNC with a re-probe round (its own start, pose and end lines), no pose line
    come: ``reprobe-start-lost`` (the plan program's start lost, the round's read: not the
    run's start) and ``reprobe-end-lost`` (the round's end lost: the run's end not read, not
    the plan program's end standing in) — where the run's start and end make its mean."""
    def r(at: str, pose: int | None, value: float | None, error: str = "",
          rnd: int = 0) -> TemperatureReading:
        return TemperatureReading("spindle", at, pose, 10.0 * (pose or 0), value, error, rnd)

    if kind == "full":
        return [r("start", None, 20.0), *[r("pose", p, 20.2 + 0.2 * p) for p in range(3)],
                r("end", None, 21.0)]
    if kind == "no-start":
        return [r("start", None, None, "opcua: BadNodeIdUnknown"),
                *[r("pose", p, 21.0 + 0.4 * p) for p in range(3)], r("end", None, 22.4)]
    if kind.startswith("reprobe"):
        lost, gone = kind == "reprobe-start-lost", NOT_PRINTED.format(where="a line")
        return [r("start", None, None if lost else 22.0, gone if lost else ""),
                *[r("pose", p, None, gone) for p in range(3)], r("end", None, 22.6),
                r("start", None, 22.8, rnd=1), r("pose", 1, None, gone, 1),
                r("end", None, 23.0 if lost else None, "" if lost else gone, 1)]
    return [r("start", None, None, NO_ANSWER), *[r("pose", p, None, DOWN) for p in range(3)],
            r("end", None, 23.5)]


KINDS = ["full", "no-start", "end-only", "reprobe-start-lost", "reprobe-end-lost"]
EXPECTED_MEAN = {"full": 20.4, "no-start": 21.4, "end-only": 23.5, "reprobe-start-lost": 23.0,
                 "reprobe-end-lost": 22.0}
EXPECTED_TEXT = {
    "full": "spindle 20.0 → 21.0 °C (+1.0 °C)",
    "no-start": "spindle 21.0 (pose 0) → 22.4 °C (end) (+1.4 °C; start not read)",
    "end-only": "spindle 23.5 °C (end only; start not read)",
    "reprobe-start-lost": "spindle 22.6 (end of the plan's program) → 23.0 °C (end) (+0.4 °C; "
                          "start not read)",
    "reprobe-end-lost": "spindle 22.0 (start) → 22.8 °C (start of re-probe 1) (+0.8 °C; end "
                        "not read)"}
EXPECTED_WHY = {  # the change limit's WARN where the change was not measured over the run
    "no-start": "not checked over the whole run: +1.4 °C over pose 0 → end only",
    "end-only": "one reading only (end)",
    "reprobe-start-lost": "not checked over the whole run: +0.4 °C over end of the plan's "
                          "program → end only",
    "reprobe-end-lost": "not checked over the whole run: +0.8 °C over start → start of "
                        "re-probe 1 only"}


@pytest.mark.parametrize("kind", KINDS)
def test_a_run_without_its_start_reading_is_said_so_everywhere(kind):
    s = summarise(readings(kind), SOURCES)["spindle"]
    a = Analysis(machine="m", links={"EX0C": LinkError(5.0, 1.0, "um")},
                 temperatures={"spindle": s})
    assert s["mean_c"] == pytest.approx(EXPECTED_MEAN[kind])
    assert channel_text("spindle", s) == EXPECTED_TEXT[kind]
    assert temperature_lines(a) == [EXPECTED_TEXT[kind]]  # the HMI card, the PDF line
    assert audit_text(a).startswith(EXPECTED_TEXT[kind] + " — from spindle: opcua")
    row = table_rows(a)[0]
    if kind == "end-only":
        assert (s["start_c"], s["change_c"], row["start"], row["change"]) == (None, None, "—",
                                                                            "—")
    elif kind == "no-start":
        assert s["start_c"] is None and row["change"] == "+1.40 (pose 0 → end)"
    # a change limit is checked only where a change was measured over the whole run
    tol = Tolerances(default_translation_um=Limit(warn=60, fail=120),
                     temperatures={"spindle": (None, None, 2.0)})
    j = judge(a, tol)
    why = [x for x in j.reasons if "temperature change spindle" in x]
    if kind == "full":
        assert j.status == "PASS" and not why, j.reasons
    else:
        assert j.status == "WARN" and why, j.reasons
        assert EXPECTED_WHY[kind] in why[0], why


def test_old_summaries_keep_their_numbers():
    """A summary stored before the fix (start_c filled with the first reading, no mean_c): the
    same text and run temperature as before."""
    old = {"source": "x", "start_c": 20.5, "end_c": 24.1, "change_c": 3.6,
           "per_pose": [{"pose": 0, "value_c": 21.0}, {"pose": 1, "value_c": 22.0}]}
    assert channel_text("spindle", old) == "spindle 20.5 → 24.1 °C (+3.6 °C)"
    a = Analysis(machine="m", links={}, temperatures={"spindle": old})
    from daemon.analysis.temperature_trend import run_temperature
    assert run_temperature(a, "spindle") == pytest.approx(21.5)
    assert run_mean_c([], 20.5, None) == 20.5 and run_mean_c([None], None, None) is None


@pytest.mark.peer
async def test_cli_and_fleet_page_show_the_same_numbers_for_a_run_without_a_start(pg, tmp_path,
                                                                                   capsys):
    dsn = fresh_db(pg)
    store = Store(tmp_path / "journal.sqlite")
    kinds = KINDS
    drainer = Drainer(store, dsn)
    try:
        for k, kind in enumerate(kinds):  # as a daemon run journals and summarises them
            rid = f"20260202-06000{k}-{kind}"
            store.new_run(rid, "mill1", "cnc", started_at=time.time() - 3600 * (9 - k),
                          state="DONE")
            for r in readings(kind):
                journal_temperature(store, rid, r)
            store.save_analysis(rid, Analysis(
                machine="thesis", links={"EX0C": LinkError(4.0 + k, 0.4, "um")},
                temperatures=summarise(temperatures(store, rid), SOURCES)))
            store.save_verdict(rid, "PASS", [], [], "")
        await drainer.drain()
        assert drainer.backlog() == 0
        cli_points = {p.run_id: p.temperature_c for p in points(
            store.trend("mill1", 10), "EX0C", "spindle")[0]}
    finally:
        await drainer.stop()
        store.close()
    cfg = write_daemon_yaml(tmp_path, token=HMI_TOKEN, extra_machine=CHANNELS)
    assert cli_main(["history", "--config", str(cfg), "--machine", "mill1",
                     "--against-temperature", "spindle", "--link", "EX0C"]) == 0
    cli_out = capsys.readouterr().out
    # the HMI's link-against-temperature (its trend API) over the same journal
    rows = thesis_rows(thesis_setup())
    svc = Service(load_daemon_config(cfg), lambda s: ReplayLink(rows, s.machine),
                  prepare=prepare_from_rows(rows))
    await svc.start()
    try:
        async with aiohttp.ClientSession(headers={"Authorization": f"Bearer {HMI_TOKEN}"}) as h, \
                h.get(svc.hmi_url + "api/machines/mill1/trend",
                      params={"against": "spindle", "link": "EX0C"}) as r:
            hmi = await r.json()
            assert r.status == 200, hmi
    finally:
        await svc.stop()
    hmi_points = {p["run_id"]: p["temperature_c"] for p in hmi["against"]["points"]}
    from tests.test_fleet_page import TOKEN, serving
    async with serving(dsn, tmp_path) as url, aiohttp.ClientSession(
            headers={"Authorization": f"Bearer {TOKEN}"}) as http:
        fleet = await fleet_against(http, url, "mill1")
        async with http.get(f"{url}/machines/mill1") as r:
            page = html.unescape(await r.text())
            assert r.status == 200, page
    fleet_points = {p["run_id"]: p["temperature_c"] for p in fleet["points"]}
    want = {f"20260202-06000{k}-{kind}": EXPECTED_MEAN[kind] for k, kind in enumerate(kinds)}
    assert cli_points == pytest.approx(want)
    assert fleet_points == pytest.approx(want)
    assert fleet_points == cli_points == hmi_points  # one definition: the same floats
    for rid, mean in want.items():
        assert f"{rid}  spindle {mean:6.2f} °C" in cli_out, cli_out
    for kind in kinds:  # the run table's cell says what the report and the HMI say
        assert EXPECTED_TEXT[kind] in page, (kind, EXPECTED_TEXT[kind])
    assert "+0.0 °C" not in page


def test_summary_fields_match_the_fleet_store_query():
    """The fleet page's raw-readings query (daemon/store/pg_temperatures.readings) picks the
    plan program's first start value read, the last program's end and the pose values in
    order: the summary picks the same ones (contracts.temperatures.run_ends), so run_mean_c
    sees the same inputs either way (the fleet half: the re-probe kinds above)."""
    rs = [TemperatureReading("spindle", "start", None, 0.0, None, "x"),
          TemperatureReading("spindle", "start", None, 1.0, 23.9),  # a start read late
          TemperatureReading("spindle", "end", None, 50.0, 24.0),
          TemperatureReading("spindle", "start", None, 60.0, 24.2, "", 1),  # a re-probe's
          TemperatureReading("spindle", "end", None, 90.0, 24.4, "", 1)]
    s = summarise(rs, SOURCES)["spindle"]
    assert (s["start_c"], s["end_c"], s["mean_c"]) == (23.9, 24.4, pytest.approx(24.15))
    assert (s["first_c"], s["first_at"], s["change_over"]) == (23.9, "start", "start → end")
    s = summarise(rs[2:], SOURCES)["spindle"]  # the run's start not read: not the re-probe's
    assert (s["start_c"], s["end_c"], s["mean_c"]) == (None, 24.4, 24.4)
    assert s["change_over"] == "end of the plan's program → end"
