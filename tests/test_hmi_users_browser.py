"""The HMI's people in headless Chromium (peer), desktop and phone: the
sign-in form with name and password, the person and role in the header, an operator's
compensation buttons refused (and the daemon's 403 shown), Start asking for the pre-flight list
(refused until every item is ticked), the pose and ball being probed shown live, the trend
charts on a date-and-time axis, and on a phone one link error's chart at a time."""

from __future__ import annotations

import asyncio
import datetime
import io
import sys
from zoneinfo import ZoneInfo

import pytest

from benchmarks.rigs.daemon_helpers import thesis_rows, thesis_setup, write_daemon_yaml
from daemon.analysis.replay_link import ReplayLink, prepare_from_rows
from daemon.config import load_daemon_config
from daemon.service.service import Service
from tests.browser import chromium, tick_preflight
from tests.cli_helpers import run_cli
from tests.test_hmi_browser import past_run

pytestmark = [pytest.mark.peer]
TOKEN = "t0k3n-for-people-0123456789"
USERS = {"olga": ("operator", "operator-pass-1"), "erik": ("engineer", "engineer-pass-2")}
TZ = "Europe/Berlin"


async def people_service(tmp_path, capsys, monkeypatch, delay_s: float = 0.0) -> Service:
    for name, (role, password) in USERS.items():
        monkeypatch.setattr(sys, "stdin", io.StringIO(password + "\n"))
        code, _, err = run_cli(["users", "--file", str(tmp_path / "users"), "add", name,
                                "--role", role, "--password-stdin"], capsys)
        assert code == 0, err
    cfg = write_daemon_yaml(tmp_path, token=TOKEN)
    cfg.write_text(cfg.read_text().replace(f"token: {TOKEN}}}",
                                           f"token: {TOKEN}, users_file: users}}"))
    rows = thesis_rows(thesis_setup())
    svc = Service(load_daemon_config(cfg), lambda s: ReplayLink(rows, s.machine,
                                                                 delay_s=delay_s),
                  prepare=prepare_from_rows(rows))
    await svc.start()
    return svc


async def test_operator_desktop_login_roles_preflight_live_pose_trend(tmp_path, capsys,
                                                                      monkeypatch):
    svc = await people_service(tmp_path, capsys, monkeypatch, delay_s=0.04)
    try:
        ended = [past_run(svc, "R1-older", 1, 30 * 3600), past_run(svc, "R2-latest", 2, 3600)]
        async with chromium(tmp_path / "profile") as cdp:
            sid = await cdp.page()
            await cdp.call("Emulation.setTimezoneOverride", sid, timezoneId=TZ)
            # the sign-in form asks for a name and a password, not the token
            await cdp.call("Page.navigate", sid, url=svc.hmi_url)
            await cdp.wait_for(sid, "location.pathname === '/login' && "
                                    "document.readyState === 'complete'")
            assert await cdp.eval(sid, "[!!document.getElementById('user'), "
                                       "!!document.getElementById('password'), "
                                       "!!document.getElementById('token')]") == \
                [True, True, False]
            await cdp.screenshot(sid, tmp_path / "people-login.png")
            await cdp.sign_in_user(sid, svc.hmi_url, "olga", "wrong-password", live=False)
            await cdp.wait_for(sid, "document.querySelector('.error') && document.querySelector"
                                    "('.error').textContent === 'Wrong name or password.'")
            await cdp.sign_in_user(sid, svc.hmi_url, "olga", USERS["olga"][1])
            assert await cdp.wait_for(sid, "document.getElementById('who').textContent") == \
                "olga · operator"
            # an operator's compensation buttons are off and say why; the daemon refuses too
            card = "document.querySelector('.machine')"
            titles = await cdp.wait_for(sid, f"[...{card}.querySelectorAll('.comp-confirm, "
                                             ".comp-rollback')].every(b => b.disabled && "
                                             "b.title) && [...document.querySelectorAll("
                                             "'.comp-confirm, .comp-rollback')].map(b => "
                                             "b.title)")
            assert titles == ["signed in as olga (operator): an engineer or admin confirms"] * 2
            refused = await cdp.eval(sid, "post('/api/compensation/rollback', {machine: "
                                          "'mill1'}).then(r => [r.ok, r.body.error])")
            assert refused == [False, "signed in as olga (operator): rolling back a "
                                      "compensation needs an engineer or admin"], refused
            # the trend: runs on a date-and-time axis, in the browser's time zone
            charts = f"[...{card}.querySelectorAll('.trend svg.chart')]"
            assert await cdp.wait_for(sid, f"{charts}.length") == 9
            ticks = await cdp.eval(sid, f"{charts}[0].querySelectorAll('.xtick').length + ' ' +"
                                        f" [...{charts}[0].querySelectorAll('.xtick text')]"
                                        ".map(t => t.textContent).join(' ')")
            local = [datetime.datetime.fromtimestamp(e - 240, ZoneInfo(TZ)) for e in ended]
            assert ticks == "2 " + " ".join(f"{d:%m-%d %H:%M}" for d in local), ticks
            width = await cdp.eval(sid, f"{charts}[0].getBoundingClientRect().width")
            assert width >= 300, width  # readable: was ~180 px wide with 9 px text
            await cdp.screenshot(sid, tmp_path / "people-trend.png")
            # Start asks for the pre-flight list; its Start is off until all is ticked
            await cdp.eval(sid, f"{card}.querySelector('.start').click(); true")
            items = await cdp.wait_for(sid, "document.getElementById('preflight').open && "
                                            "[...document.querySelectorAll('.pf-items li')]"
                                            ".map(li => li.textContent.trim())")
            assert items[:3] == ["Touch probe in the spindle, switched on",
                                 "Balls clean and tight on their stems, artefact clamped",
                                 "Doors closed"] and len(items) == 4, items
            assert svc.sessions["mill1"].run_id is None  # nothing started yet
            await tick_preflight(cdp, sid, tmp_path / "people-preflight.png")
            # live: the pose and ball being probed
            seen: set[tuple[str, str]] = set()
            shot = False
            async with asyncio.timeout(120):
                while True:
                    got = await cdp.eval(sid, f"[{card}.querySelector('.state').textContent, "
                                              f"{card}.querySelector('.probing').hidden, "
                                              f"{card}.querySelector('.probing').textContent, "
                                              f"{card}.querySelector('.probing').dataset.pose,"
                                              f" {card}.querySelector('.probing').dataset.ball]")
                    if got[0] == "CAPTURE" and not got[1]:
                        assert got[2].startswith(f"Probing pose {got[3]}, ball {got[4]}, "
                                                 "touch "), got
                        seen.add((got[3], got[4]))
                        if not shot:
                            await cdp.screenshot(sid, tmp_path / "people-live-pose.png")
                            shot = True
                    if got[0] == "IDLE" and seen:
                        break
                    await asyncio.sleep(0.05)
            assert len({p for p, _ in seen}) >= 3 and len({b for _, b in seen}) >= 3, seen
            assert await cdp.eval(sid, f"{card}.querySelector('.probing').hidden")
            run = svc.store.runs("mill1", 1)[0]
            assert run.started_by == "olga"
            who = await cdp.wait_for(sid, "[...document.querySelectorAll('#history tbody tr')]"
                                          f".filter(r => r.dataset.run === '{run.id}')"
                                          ".map(r => r.cells[2].textContent)[0]")
            assert who == "olga (hmi)", who  # the "Last runs" row names the person
    finally:
        await svc.stop()


async def test_engineer_on_a_phone_one_chart_at_a_time(tmp_path, capsys, monkeypatch):
    svc = await people_service(tmp_path, capsys, monkeypatch)
    try:
        past_run(svc, "R1-older", 1, 30 * 3600)
        past_run(svc, "R2-latest", 2, 3600)
        async with chromium(tmp_path / "profile") as cdp:
            sid = await cdp.page()
            await cdp.call("Emulation.setDeviceMetricsOverride", sid, width=390, height=844,
                           deviceScaleFactor=2, mobile=True)
            await cdp.sign_in_user(sid, svc.hmi_url, "erik", USERS["erik"][1])
            assert await cdp.wait_for(sid, "document.getElementById('who').textContent") == \
                "erik · engineer"
            shown = ("[...document.querySelectorAll('.trend svg.chart')].filter(s => "
                     "getComputedStyle(s).display !== 'none').map(s => [s.dataset.name, "
                     "Math.round(s.getBoundingClientRect().width)])")
            first = await cdp.wait_for(sid, f"{shown}.length === 1 && {shown}")
            assert first[0][0] == "EA0B" and first[0][1] >= 300, first  # one, nearly full width
            pick = "document.querySelector('.trend-pick')"
            assert await cdp.eval(sid, f"getComputedStyle({pick}).display") == "block"
            await cdp.eval(sid, f"{pick}.value = 'EX0C'; {pick}.dispatchEvent(new Event("
                                "'change')); true")
            assert [n for n, _ in await cdp.eval(sid, shown)] == ["EX0C"]
            assert await cdp.eval(sid, "document.documentElement.scrollWidth") <= 390
            # an engineer's compensation buttons carry no refusal
            assert await cdp.eval(sid, "[...document.querySelectorAll('.comp-confirm, "
                                       ".comp-rollback')].map(b => b.title)") == ["", ""]
            await cdp.screenshot(sid, tmp_path / "people-phone.png", whole_page=True)
    finally:
        await svc.stop()
