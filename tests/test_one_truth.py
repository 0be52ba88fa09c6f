"""One run, one story: runs made by the real daemon against the simulated
CNC over OPC UA (thesis machine, Table B.2 errors, its Siemens section), then every surface is
read — the HTML report, the PDF's text (pdftotext), the JSON, the HMI API, the compensation
panel's API, `rumba history` and `rumba compensate`, and the fleet page over a real
PostgreSQL — and the same figures are compared, each with its definition beside it; drift is
judged against a baseline a person set on the HMI, and "drift not checked: no baseline" is said
where there is none."""

from __future__ import annotations

import asyncio
import html as html_lib
import json
import re
import shutil
import subprocess
from pathlib import Path

import aiohttp
import pytest

from benchmarks.rigs.hmi_compensation import TOKEN, bearer, world
from daemon.analysis.figures import DEFINITIONS, LABELS, VOLUMETRIC, link_label, run_figures
from daemon.compensation.propose import controller_model, reidentify
from daemon.store import baselines
from daemon.store.drain import RUN_COLS
from daemon.store.pg import PgStore, RunBatch
from tests.browser import chromium
from tests.cli_helpers import run_cli

pytestmark = [pytest.mark.peer]


def flat(text: str) -> str:
    """Text with tags dropped, entities decoded and white space folded (layout-free)."""
    return " ".join(html_lib.unescape(re.sub(r"<[^>]+>", " ", text)).split())


def pdf_text(pdf: Path) -> str:
    exe = shutil.which("pdftotext")
    if exe is None:
        pytest.skip("pdftotext not installed (poppler-utils)")
    out = subprocess.run([exe, str(pdf), "-"], check=True, capture_output=True, text=True,
                         timeout=60).stdout
    return " ".join(out.split())


async def run_to_end(svc, http: aiohttp.ClientSession) -> str:
    r = await http.post(svc.hmi_url + "api/machines/mill1/start", headers=bearer())
    assert r.status == 202, await r.text()
    run_id = (await r.json())["run_id"]
    async with asyncio.timeout(180):
        await svc.sessions["mill1"].wait()
    assert svc.store.run(run_id).state == "DONE", svc.store.run(run_id)
    return run_id


async def fleet_page(tmp: Path, store, run_id: str) -> str:
    """The run copied to a real PostgreSQL as the drainer copies it, and its machine's
    fleet page served by the fleet app."""
    from aiohttp import web

    from daemon.fleet.app import create_fleet_app
    from tests.fleet_helpers import fresh_db, start_postgres

    pg = start_postgres()
    try:
        dsn = fresh_db(pg)
        db = store.db
        run = db.execute(f"SELECT {', '.join(RUN_COLS)} FROM runs WHERE id=?",
                         (run_id,)).fetchone()
        ps = await PgStore.connect(dsn)
        try:
            await ps.write_run(RunBatch(
                run=tuple(run), analysis=db.execute("SELECT analysis FROM estimates WHERE "
                                                    "run_id=?", (run_id,)).fetchone()[0],
                verdict=db.execute("SELECT status, reasons, checks, written_back FROM "
                                   "verdicts WHERE run_id=?", (run_id,)).fetchone()))
        finally:
            await ps.close()
        app = create_fleet_app(dsn, "fleet-t0k3n-0123456789", reports_dirs=[tmp],
                               bind_host="127.0.0.1")
        runner = web.AppRunner(app, handle_signals=False)
        await runner.setup()
        site = web.TCPSite(runner, "127.0.0.1", 0)
        await site.start()
        try:
            url = f"http://127.0.0.1:{runner.addresses[0][1]}/machines/mill1"
            async with aiohttp.ClientSession() as http:
                r = await http.get(url, headers={"Authorization":
                                                 "Bearer fleet-t0k3n-0123456789"})
                assert r.status == 200, await r.text()
                return await r.text()
        finally:
            await runner.cleanup()
    finally:
        pg.close()


async def test_every_surface_tells_the_same_numbers_of_one_run(tmp_path, capsys):
    # the start-of-shift plan: held-out poses and a pose probed again (the run's estimate uses
    # both visits; a refit of the stored centres, the panel's before, used only the first)
    async with world(tmp_path, plan="shift_start_14poses") as svc, \
            aiohttp.ClientSession() as http:
        first = await run_to_end(svc, http)
        # no baseline yet: said on the verdict, the report and the HMI, never silently dropped
        v = svc.sessions["mill1"].verdict
        assert any(r.startswith("drift not checked: no baseline") for r in v["reasons"]), v
        assert v["baseline"] is None
        first_html = flat(svc.store.report(first)[0].read_text())
        assert "none set: drift not checked" in first_html
        # an engineer accepts the first run as the baseline on the HMI (who and when journaled)
        r = await http.post(svc.hmi_url + "api/machines/mill1/baseline", headers=bearer(),
                            json={"run_id": first, "by": "Anna Berg", "note": "after service"})
        assert r.status == 200, await r.text()
        base = (await r.json())["baseline"]
        assert base["run_id"] == first and base["by"] == "Anna Berg" and base["state"] == \
            "confirmed"
        run_id = await run_to_end(svc, http)
        store = svc.store
        a = store.analysis(run_id)
        assert a.reference_run == first
        vol = run_figures(a)[0]
        assert vol.key == VOLUMETRIC and vol.value is not None and vol.value > 50
        shown = f"{LABELS[VOLUMETRIC]} {vol.value:.1f} µm"
        definition = DEFINITIONS[VOLUMETRIC]
        links = {n: (f"{x.value:+.2f}", f"{x.std:.2f}") for n, x in a.links.items()}
        checks = store.verdict(run_id)["checks"]
        drift = [c for c in checks if c["quantity"].endswith(" drift")]
        assert drift and all(c["reference_run"] == first for c in drift), drift

        # the JSON report
        html_path, json_path = store.report(run_id)
        doc = json.loads(json_path.read_text())
        assert doc["figures"][0] == {"key": VOLUMETRIC, "label": LABELS[VOLUMETRIC],
                                     "value": vol.value, "unit": "µm", "definition": definition}
        assert {n: (f"{x['value']:+.2f}", f"{x['std']:.2f}")
                for n, x in doc["analysis"]["links"].items()} == links
        assert doc["audit"]["baseline"].startswith(f"run {first} of ")
        assert "confirmed by Anna Berg" in doc["audit"]["baseline"]
        # the HTML report: the figure, its definition, each link with its names and numbers
        page = flat(html_path.read_text())
        assert shown in page and definition in page
        assert f"{LABELS[VOLUMETRIC]} {vol.value:.1f} µm {definition}" in page
        for n, (value, std) in links.items():
            assert f"{link_label(n, _spec(svc))} {value} {std}" in page, n
        assert "EX0C — X offset of the C axis line, Siemens $TC_CARR15[1] (c-x)" in page
        assert f"Drift baseline run {first} of " in page and "confirmed by Anna Berg" in page
        # the PDF (its text as pdftotext reads it)
        text = pdf_text(html_path.with_suffix(".pdf"))
        assert shown in text and " ".join(definition.split()) in text
        for n, (value, std) in links.items():
            assert f"{value} {std}" in text and n in text, n
        assert f"run {first} of " in text
        # the HMI API: the live verdict and the journaled runs
        st = await (await http.get(svc.hmi_url + "api/status", headers=bearer())).json()
        hv = st["mill1"]["verdict"]
        assert shown in hv["summary"] and hv["figures"][0]["value"] == vol.value
        assert hv["figures"][0]["definition"] == definition
        assert hv["baseline"]["run_id"] == first
        runs = await (await http.get(svc.hmi_url + "api/runs", headers=bearer())).json()
        row = next(x for x in (runs["runs"] if isinstance(runs, dict) else runs)
                   if x["id"] == run_id)
        assert shown in row["summary"]
        bl = await (await http.get(svc.hmi_url + "api/machines/mill1/baseline",
                                   headers=bearer())).json()
        assert bl["text"].startswith(f"drift judged against run {first} of ")
        # the compensation panel: the same figure, and the report's link values
        r = await http.get(svc.hmi_url + "api/compensation?machine=mill1", headers=bearer())
        assert r.status == 200, await r.text()
        p = (await r.json())["proposal"]
        assert p["figures"][0]["value"] == vol.value and p["figures"][0]["label"] == \
            LABELS[VOLUMETRIC]
        assert p["links_from"] == "run"
        # the refit of the stored centres (first visit per pose) the panel showed before
        # differs on this run: the comparison below would fail on it
        setup = svc.sessions["mill1"].setup
        model = controller_model(setup, store, before=store.run(run_id).started_at,
                                 check_hal=False)
        refit = reidentify(setup, store, run_id, model)[0].links_si()
        assert max(abs(refit[n][0] - a.links[n].value) for n in a.links) > 0.02
        for ln in p["links"]:
            assert f"{ln['identified']:+.2f}" == links[ln["name"]][0], ln
        names = [f["label"] for f in p["figures"]]
        assert not any("compensable" in x for x in names), names
        before = next(f for f in p["figures"] if f["key"] == "link_caused_max_um")
        after = next(f for f in p["figures"] if f["key"] == "predicted_after_max_um")
        assert after["value"] <= before["value"] <= vol.value  # explained in one sentence
        # the CLI: rumba history and rumba compensate
        cfg = str(tmp_path / "daemon.yaml")
        code, out, err = run_cli(["history", "--config", cfg, "--machine", "mill1"], capsys)
        assert code == 0, err
        one = " ".join(out.split())
        assert f"{vol.value:.1f}" in next(ln for ln in out.splitlines() if run_id in ln)
        assert " ".join(f"{LABELS[VOLUMETRIC]}: {definition}.".split()) in one
        assert f"mill1: drift judged against baseline run {first} of " in one
        code, out, err = run_cli(["compensate", "--config", cfg, run_id], capsys)
        assert code == 0, err
        assert f"{shown} — " in out
        for n, (value, _) in links.items():
            assert re.search(rf"^\s+{n}\s+{re.escape(value)} ", out, re.M), (n, out)
        # the HMI page itself, in Chromium: the card and the compensation panel
        async with chromium(tmp_path / "profile") as cdp:
            sid = await cdp.page()
            await cdp.sign_in(sid, svc.hmi_url, TOKEN)
            card = "document.querySelector('.machine')"
            await cdp.wait_for(sid, f"{card}.querySelector('.summary').textContent"
                                    f".includes({json.dumps(shown)})")
            assert definition in await cdp.eval(
                sid, f"{card}.querySelector('.definition').textContent")
            assert f"baseline run {first} of " in await cdp.eval(
                sid, f"{card}.querySelector('.baseline').textContent")
            dist = f"{card}.querySelector('.comp .comp-dist').textContent"
            await cdp.wait_for(sid, f"{dist}.includes({json.dumps(shown)})")
            assert definition in await cdp.eval(sid, dist)
            # item 2 on the page: accept this run as the baseline (the dialogs answered)
            btn = f"{card}.querySelector('.set-baseline')"
            await cdp.wait_for(sid, f"!{btn}.hidden")
            await cdp.eval(sid, "window.confirm = () => true; window.prompt = () => "
                                "'Jo Keller'; true")
            await cdp.eval(sid, f"{btn}.click(); true")
            await cdp.wait_for(sid, f"{card}.querySelector('.message').textContent"
                                    ".startsWith('Baseline now: run ')")
            assert await cdp.eval(sid, f"{btn}.hidden")
        b = baselines.current(store, "mill1")
        assert (b.run_id, b.by) == (run_id, "Jo Keller") and "via token-login" in b.note
        # the fleet page (the run as the drainer copies it to PostgreSQL)
        fleet = flat(await fleet_page(tmp_path, store, run_id))
        assert shown in fleet and f"{LABELS[VOLUMETRIC]}: {definition}." in fleet


def _spec(svc):
    from daemon.compensation.propose import spec_of

    return spec_of(svc.sessions["mill1"].setup)
