"""The rotary axes' indexing repeatability behind a run's link u on every
screen with one text: the HTML report, its JSON and PDF (pdftotext), the HMI's verdict card
data and its run API, the fleet page's run table (real PostgreSQL) — for a run whose stated
value is used, one whose stated value the run overrides (with its p and the warning), and an
analysis JSON written before the field."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import aiohttp
import yaml
from aiohttp import web

from benchmarks.rigs.daemon_helpers import CONFIG, thesis_rows, thesis_setup, write_daemon_yaml
from daemon.analysis.replay_link import ReplayLink, prepare_from_rows
from daemon.analysis.result import Analysis
from daemon.config import load_daemon_config
from daemon.hmi.app import create_app
from daemon.reports.index_scatter import NONE, TITLE, index_scatter_lines
from daemon.reports.report import pdf_path, write_report
from daemon.service.service import Service
from daemon.store.journal import Store
from tests.test_estimate_stated import _analyse, scatter_log  # noqa: F401  (a fixture)
from tests.test_one_truth import flat, fleet_page, pdf_text

TOKEN = "t0k3n-for-index-scatter-0123"
BEARER = {"Authorization": f"Bearer {TOKEN}"}


def _squeezed(text: str) -> str:
    """Without any white space: the PDF wraps a line anywhere, even after a hyphen."""
    return "".join(text.split())


def _on_every_page(lines: list[str], html: str, doc: dict, pdf: str) -> None:
    assert doc["index_scatter"]["lines"] == lines and doc["index_scatter"]["title"] == TITLE
    page = flat(html)
    for line in lines:
        assert line in page, (line, page[page.find(TITLE):][:800])
        assert _squeezed(line) in _squeezed(pdf), line


async def _api(store: Store, run_ids: list[str]) -> dict[str, dict]:
    """GET /api/runs/<id> of each run from the HMI app on a free loopback port."""
    runner = web.AppRunner(create_app({}, store, TOKEN, bind_host="127.0.0.1"),
                           handle_signals=False)
    await runner.setup()
    site = web.TCPSite(runner, "127.0.0.1", 0)
    await site.start()
    try:
        url = f"http://127.0.0.1:{runner.addresses[0][1]}/api/runs/"
        out = {}
        async with aiohttp.ClientSession() as http:
            for rid in [*run_ids, "no-such-run"]:
                r = await http.get(url + rid, headers=BEARER)
                out[rid] = await r.json() if r.status == 200 else r.status
        return out
    finally:
        await runner.cleanup()


async def test_stated_overridden_and_old_analyses_on_report_pdf_and_run_api(
        scatter_log, tmp_path, capsys):  # noqa: F811
    """A 10 µrad B/C index scatter: stated 40 (used), stated 1 (overridden on both axes, the
    warning shown), and the overridden run's JSON without the field (an old analysis); `rumba
    analyze` prints the axis lines too."""
    (tmp_path / "m").mkdir()
    used = _analyse(scatter_log, tmp_path / "m", {"B": 40, "C": 40})
    printed = {"r-used": " ".join(capsys.readouterr().out.split())}
    over = _analyse(scatter_log, tmp_path / "m", {"B": 1, "C": 1})
    printed["r-over"] = " ".join(capsys.readouterr().out.split())
    old = json.loads(json.dumps(over))
    del old["estimation"]["index_scatter"]
    analyses = {f"r-{k}": Analysis.from_json(v) for k, v in
                (("used", used), ("over", over), ("old", old))}
    store = Store(tmp_path / "journal.sqlite")
    texts = {}
    for rid, a in analyses.items():
        store.new_run(rid, "mill1", "cli", state="DONE")
        store.save_analysis(rid, a)
        html, js = write_report(tmp_path / "reports", store.run(rid), a, None, [], [])
        store.save_report(rid, html, js)
        texts[rid] = (html.read_text(), json.loads(js.read_text()), pdf_text(pdf_path(html)))
    api = await _api(store, list(analyses))
    assert api["no-such-run"] == 404

    ix = {x.axis: x for x in analyses["r-used"].estimation.index_scatter}
    lines = index_scatter_lines(analyses["r-used"])
    assert lines == [
        f"{a} indexing repeatability: {ix[a].estimated_urad:.1f} ± {ix[a].std_urad:.1f} µrad "
        f"estimated from 14 visits, machine file states 40 µrad, used: stated" for a in "BC"]
    assert ix["B"].estimated_urad > 5.0  # the 10 µrad the run shows, not the stated 40

    lines = index_scatter_lines(analyses["r-over"])
    assert len(lines) == 4, lines  # per axis its line, then each axis' warning
    for a, line in zip("BC", lines[:2], strict=True):
        x = next(x for x in analyses["r-over"].estimation.index_scatter if x.axis == a)
        assert line.startswith(f"{a} indexing repeatability: {x.estimated_urad:.1f} ± ")
        assert line.endswith(f"machine file states 1 µrad, used: estimated (the stated 1 µrad "
                             f"overridden: one-sided likelihood-ratio test p = "
                             f"{x.p_stated:.2g} < 0.01)")
    assert [w[:30] for w in lines[2:]] == ["Warning: B indexing repeatabil",
                                           "Warning: C indexing repeatabil"]
    assert all("machine file states 1 (likelihood-ratio test" in w for w in lines[2:])
    assert index_scatter_lines(analyses["r-old"]) == [NONE]

    for rid, out in printed.items():  # the console wraps: compared with white space folded
        for line in index_scatter_lines(analyses[rid]):
            assert (" ".join(line.split()) in out) != line.startswith("Warning: "), (line, out)
    for rid, a in analyses.items():
        want = index_scatter_lines(a)
        _on_every_page(want, *texts[rid])
        assert api[rid]["index_scatter"]["lines"] == want
        assert api[rid]["id"] == rid and api[rid]["report"] == f"/reports/{rid}.html"


async def test_the_daemons_card_and_run_api_carry_the_reports_text(tmp_path):
    """A run of the daemon (replayed thesis centres, no index scatter) on a machine file
    stating 40 µrad: the live verdict the card shows, the run API and the report agree."""
    data = yaml.safe_load((CONFIG / "machines/thesis_wcbxfzyt.yaml").read_text())
    data["rotary_repeatability_urad"] = {"B": 40, "C": 40}
    (tmp_path / "machine.yaml").write_text(yaml.safe_dump(data))
    path = write_daemon_yaml(tmp_path, token=TOKEN)
    path.write_text(path.read_text().replace(str(CONFIG / "machines/thesis_wcbxfzyt.yaml"),
                                             str(tmp_path / "machine.yaml")))
    rows = thesis_rows(thesis_setup())
    svc = Service(load_daemon_config(path), lambda s: ReplayLink(rows, s.machine),
                  prepare=prepare_from_rows(rows))
    await svc.start()
    try:
        async with aiohttp.ClientSession() as http:
            r = await http.post(svc.hmi_url + "api/machines/mill1/start", headers=BEARER)
            assert r.status == 202, await r.text()
            run_id = (await r.json())["run_id"]
            async with asyncio.timeout(120):
                await svc.sessions["mill1"].wait()
            assert svc.store.run(run_id).state == "DONE", svc.store.run(run_id)
            status = await (await http.get(svc.hmi_url + "api/status", headers=BEARER)).json()
            detail = await (await http.get(svc.hmi_url + f"api/runs/{run_id}",
                                           headers=BEARER)).json()
            assert detail["report"] == f"/reports/{run_id}.html"
            html = await (await http.get(svc.hmi_url + detail["report"][1:], headers=BEARER)).text()
            doc = await (await http.get(svc.hmi_url + f"reports/{run_id}.json",
                                        headers=BEARER)).json()
        want = index_scatter_lines(svc.store.analysis(run_id))
        assert [w[:25] for w in want] == [f"{a} indexing repeatability:" for a in "BC"], want
        assert all(w.endswith(" µrad estimated from 7 visits, machine file states 40 µrad, "
                              "used: stated") for w in want), want
        assert status["mill1"]["verdict"]["index_scatter"] == want
        assert detail["index_scatter"]["lines"] == want
        _on_every_page(want, html, doc, pdf_text(Path(svc.store.report(run_id)[0])
                                                 .with_suffix(".pdf")))
        # the fleet page's run table, the run copied to a real PostgreSQL as the drainer does
        page = await fleet_page(tmp_path, svc.store, run_id)
        cell = page.split('<td class="index-scatter">', 1)[1].split("</td>", 1)[0]
        assert flat(cell) == "; ".join(want), cell
    finally:
        await svc.stop()
