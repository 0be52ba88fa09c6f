"""The HMI's trend and PDF endpoints over real HTTP: per link error its unit, values and the
limits the judge applies (its own or the default of its kind), bounded query values, and the
report PDF served beside the HTML."""

from __future__ import annotations

import time

import aiohttp

from benchmarks.rigs.daemon_helpers import thesis_rows, thesis_setup, write_daemon_yaml
from benchmarks.rigs.report_helpers import journal_run
from daemon.analysis.replay_link import ReplayLink, prepare_from_rows
from daemon.config import load_daemon_config
from daemon.service.service import Service

TOKEN = "t0k3n-for-trend-api-0123456789"


async def test_trend_json_units_limits_and_bounds(tmp_path):
    path = write_daemon_yaml(tmp_path, token=TOKEN)
    path.write_text(path.read_text().replace(
        "default_rotation_urad:", "links: {EB0Z: {warn: 20, fail: 40}}\n      "
                                  "default_rotation_urad:"))
    rows = thesis_rows(thesis_setup())
    svc = Service(load_daemon_config(path), lambda s: ReplayLink(rows, s.machine),
                  prepare=prepare_from_rows(rows))
    await svc.start()
    try:
        for k in range(3):
            journal_run(svc.store, thesis_setup(), f"T{k}", k, time.time() - (3 - k) * 3600)
        async with aiohttp.ClientSession(
                headers={"Authorization": f"Bearer {TOKEN}"}) as http:
            r = await http.get(svc.hmi_url + "api/machines/mill1/trend")
            assert r.status == 200
            t = await r.json()
            assert [x["id"] for x in t["runs"]] == ["T0", "T1", "T2"]
            s = {x["name"]: x for x in t["series"]}
            assert [x["unit"] for x in t["series"]][:7] == ["µrad"] * 7  # rotations first
            assert (s["EB0Z"]["warn"], s["EB0Z"]["fail"]) == (20, 40)  # its own limit
            assert (s["EA0B"]["warn"], s["EA0B"]["fail"]) == (40, 80)  # default rotation
            assert (s["EX0C"]["unit"], s["EX0C"]["warn"], s["EX0C"]["fail"]) == ("µm", 150, 300)
            assert s["volumetric max"]["two_sided"] is False and len(s["EX0C"]["values"]) == 3
            assert s["EX0C"]["values"][2] == svc.store.analysis("T2").links["EX0C"].value
            r = await http.get(svc.hmi_url + "api/machines/mill1/trend?limit=2")
            assert [x["id"] for x in (await r.json())["runs"]] == ["T1", "T2"]
            for bad in ("1", "201", "x", "-3"):
                r = await http.get(svc.hmi_url + f"api/machines/mill1/trend?limit={bad}")
                assert r.status == 400 and "limit must be an integer from 2 to 200" in \
                    await r.text()
            assert (await http.get(svc.hmi_url + "api/machines/nope/trend")).status == 404
            # no report yet for T2: no PDF either; a bad id never reaches the store
            assert (await http.get(svc.hmi_url + "reports/T2.pdf")).status == 404
            assert (await http.get(svc.hmi_url + "reports/..%2Fx.pdf")).status == 404
            runs = await (await http.get(svc.hmi_url + "api/runs")).json()
            assert runs[0]["pdf"] is None and runs[0]["report"] is None
    finally:
        await svc.stop()
