"""The operator page in headless Chromium (peer) with temperature channels: the trend
offers a link error against a recorded temperature (one dot per run, the fitted line, r and the
slope ± u), and the verdict card of a run says what each channel read — or why it was not read."""

from __future__ import annotations

import pytest

from benchmarks.rigs.daemon_helpers import thesis_rows, thesis_setup, write_daemon_yaml
from daemon.analysis.replay_link import ReplayLink, prepare_from_rows
from daemon.config import load_daemon_config
from daemon.reports.index_scatter import NONE
from daemon.service.service import Service
from tests.browser import chromium
from tests.test_temperature_trend import CHANNELS, fill

pytestmark = [pytest.mark.peer]
TOKEN = "t0k3n-for-temperature-browser-01"


async def test_link_against_temperature_chart_and_the_cards_temperatures(tmp_path):
    fill(tmp_path, slope=1.5)
    path = write_daemon_yaml(tmp_path, token=TOKEN, extra_machine=CHANNELS)
    rows = thesis_rows(thesis_setup())
    svc = Service(load_daemon_config(path), lambda s: ReplayLink(rows, s.machine),
                  prepare=prepare_from_rows(rows))
    await svc.start()
    try:
        async with chromium(tmp_path / "profile") as cdp:
            sid = await cdp.page()
            await cdp.sign_in(sid, svc.hmi_url, TOKEN)
            against = "document.querySelector('.machine .against')"
            await cdp.wait_for(sid, f"{against} && {against}.querySelector('.against-text')"
                                    ".textContent.length > 0")
            await cdp.eval(sid, f"(() => {{ const s = {against}.querySelector('.against-link');"
                                "s.value = 'EX0C'; s.dispatchEvent(new Event('change')); "
                                "return true; })()")
            text = await cdp.wait_for(sid, f"{against}.querySelector('.against-text')"
                                           ".textContent.startsWith('EX0C against spindle') && "
                                           f"{against}.querySelector('.against-text').textContent")
            dots = await cdp.eval(sid, f"{against}.querySelectorAll('svg circle.pt').length")
            line = await cdp.eval(sid, f"{against}.querySelectorAll('svg line.line').length")
            assert dots == 30 and line == 1, (dots, line)
            assert "r = +0.9" in text and "µm/°C" in text and " ± " in text, text
            # the trend's own charts are untouched: one per link error and the volumetric max
            charts = await cdp.eval(sid, "document.querySelectorAll('.machine .trend "
                                         "svg.chart').length")
            assert charts == 2, charts  # EB0C and EX0C, the links of the filled runs
            # the card's last verdict from the journal (r999, analysed before the index
            # scatter was recorded): the run API's text says there is none, never silence
            ix = ("[...document.querySelectorAll('.machine .index-scatter li')]"
                  ".map(li => li.textContent)")
            assert await cdp.wait_for(sid, ix) == [NONE]
            # a run: the replayed link has no sensor, the card says so with the reason
            svc.sessions["mill1"].start("cli")  # the page's start asks its checklist first
            temps = await cdp.wait_for(sid, "(document.querySelector('.machine .temperatures')"
                                            " || {}).textContent")
            assert temps.startswith("Temperatures: spindle not read (") and \
                "cannot read temperature channel spindle" in temps, temps
            # the rotary axes' indexing repeatability, the report's own lines
            want = svc.sessions["mill1"].verdict["index_scatter"]
            assert want[0].startswith("B indexing repeatability: ") and \
                "machine file states none, used: estimated" in want[0], want
            assert await cdp.wait_for(sid, f"(l => l[0] !== {NONE!r} && l)({ix})") == want
    finally:
        await svc.stop()
