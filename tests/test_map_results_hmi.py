"""Maps of the linear axes on the operator page (real HTTP on a free loopback port): the
journaled map's figures, verdict and report links (``/api/maps``), its report and map file
served by id only while their hash is the journaled one, and the page's table in headless
Chromium."""

from __future__ import annotations

import aiohttp
import pytest

from daemon.store import map_results
from tests.browser import chromium
from tests.map_result_helpers import journaled_map
from tests.test_hmi import TOKEN, bearer, service  # noqa: F401 (service: the fixture)
from tests.test_map_cli import files  # noqa: F401 (files: the fixture)


@pytest.fixture(scope="module")
def fitted(files, tmp_path_factory):  # noqa: F811
    tmp = tmp_path_factory.mktemp("maphmi")
    _, mjson, rep, _ = journaled_map(tmp, files[1])
    return mjson, rep


async def test_the_api_serves_the_maps_figures_and_its_files(service, fitted):  # noqa: F811
    mjson, rep = fitted
    m = map_results.record_map_result(service.store, None, mjson, rep, machine="mill1")
    url = service.hmi_url.rstrip("/")
    async with aiohttp.ClientSession(headers=bearer()) as http:
        async with http.get(f"{url}/api/maps?machine=mill1") as r:
            assert r.status == 200
            (d,) = await r.json()
        assert (d["id"], d["kind"], d["machine"], d["verdict"]) == (m.id, "map", "mill1",
                                                                    "WARN")
        assert d["volumetric_max_um"] == pytest.approx(m.volumetric_max_um, rel=1e-12)
        assert d["volumetric_max_u_um"] == pytest.approx(m.volumetric_max_u_um, rel=1e-12)
        assert d["covered_mm"] == m.figures["covered_mm"]
        assert d["unobservable"] == m.figures["unobservable"]
        assert d["report"] == f"/maps/{m.id}/map.html" and d["pdf"] == f"/maps/{m.id}/map.pdf"
        assert str(rep) not in str(d)  # the daemon's paths stay on the daemon
        async with http.get(url + d["report"]) as r:
            assert r.status == 200 and "text/html" in r.headers["Content-Type"]
            assert "script-src" not in r.headers["Content-Security-Policy"]
            assert await r.read() == (rep / "map.html").read_bytes()
        async with http.get(url + d["pdf"]) as r:
            assert r.status == 200 and (await r.read()).startswith(b"%PDF")
        async with http.get(url + d["json"]) as r:
            assert r.status == 200 and await r.read() == mjson.read_bytes()
        for bad in ("/maps/no-such-map/map.html", "/maps/..%2F..%2Fetc/map.html",
                    f"/maps/{m.id}/other.html", "/api/maps?limit=0"):
            async with http.get(url + bad) as r:
                assert r.status in (400, 404), (bad, r.status)
        # a report changed since it was journaled is not served as the journaled one
        html = rep / "map.html"
        keep = html.read_bytes()
        try:
            html.write_bytes(keep.replace(b"rumba", b"rumbx", 1))
            async with http.get(url + d["report"]) as r:
                assert r.status == 409 and "changed since it was journaled" in await r.text()
        finally:
            html.write_bytes(keep)
    async with aiohttp.ClientSession() as http, http.get(f"{url}/api/maps") as r:
        assert r.status == 401  # behind the page's sign-in like every API


@pytest.mark.peer
async def test_the_page_lists_the_map_with_its_figures(service, fitted, tmp_path):  # noqa: F811
    mjson, rep = fitted
    m = map_results.record_map_result(service.store, None, mjson, rep, machine="mill1")
    async with chromium(tmp_path / "profile") as cdp:
        sid = await cdp.page()
        await cdp.sign_in(sid, service.hmi_url, TOKEN)
        rows = "[...document.querySelectorAll('#map-history tbody tr')]"
        got = await cdp.wait_for(sid, f"{rows}.length === 1 && !document.getElementById("
                                      f"'maps').hidden && {rows}.map(r => [r.dataset.map, "
                                      "r.querySelector('.map-vmax').textContent, "
                                      "r.cells[7].textContent, "
                                      "r.querySelector('a').getAttribute('href')])")
        assert got == [[m.id, f"{m.volumetric_max_um:.1f} ± {m.volumetric_max_u_um:.1f}",
                        "WARN", f"/maps/{m.id}/map.html"]], got
