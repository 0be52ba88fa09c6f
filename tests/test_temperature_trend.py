"""A link error against a recorded temperature over the runs: ``rumba history
--against-temperature`` finds the slope a shop planted (EX0C moving 1.5 µm/°C with the spindle)
within its stated 2u, states r, agrees with scipy's linregress, and says so when there is none."""

from __future__ import annotations

import time

import numpy as np
import pytest
from scipy import stats

from benchmarks.rigs.daemon_helpers import write_daemon_yaml
from daemon.analysis.result import Analysis, LinkError
from daemon.analysis.temperature_trend import fit, points
from daemon.cli.main import main as cli_main
from daemon.store.journal import Store

CHANNELS = "    temperatures: [{name: spindle, address: /Channel/Temperatures/Z}]"
T0 = time.mktime((2026, 1, 5, 6, 0, 0, 0, 0, -1))


def analysis(temp_c: float, ex0c: float) -> Analysis:
    per_pose = [{"pose": p, "t_s": 20.0 * p, "value_c": temp_c + 0.1 * (p - 3)} for p in range(7)]
    return Analysis(machine="thesis", links={
        "EX0C": LinkError(ex0c, 0.4, "um"), "EB0C": LinkError(3.0, 1.0, "urad")},
        temperatures={"spindle": {"source": "spindle: opcua /Channel/Temperatures/Z",
                                  "start_c": temp_c - 0.3, "end_c": temp_c + 0.3,
                                  "per_pose": per_pose}})


def fill(tmp_path, slope: float, n: int = 30, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    temps = 18.0 + 8.0 * rng.random(n)
    ex0c = 5.0 + slope * (temps - 20.0) + rng.normal(0.0, 0.8, n)
    store = Store(tmp_path / "journal.sqlite")
    with store.transaction():
        for k in range(n):
            rid = f"r{k:03d}"
            store.new_run(rid, "mill1", "cnc", started_at=T0 + 86400 * k, state="DONE")
            store.save_analysis(rid, analysis(float(temps[k]), float(ex0c[k])))
            store.save_verdict(rid, "PASS", [], [], "")
        store.new_run("r999", "mill1", "cnc", started_at=T0 + 86400 * n, state="DONE")
        store.save_analysis("r999", Analysis(machine="thesis", links={  # no channel: left out
            "EX0C": LinkError(99.0, 0.4, "um")}))
        store.save_verdict("r999", "PASS", [], [], "")
    store.close()
    return temps, ex0c


def test_planted_slope_found_within_2u_with_r_and_the_plot(tmp_path, capsys):
    temps, _ = fill(tmp_path, slope=1.5)
    cfg = write_daemon_yaml(tmp_path, extra_machine=CHANNELS)
    png = tmp_path / "ex0c.png"
    code = cli_main(["history", "--config", str(cfg), "--machine", "mill1", "--limit", "100",
                     "--against-temperature", "spindle", "--link", "EX0C", "--plot", str(png)])
    out = capsys.readouterr().out
    assert code == 0, out
    assert out.count(" spindle ") == 30 and "r999" not in out  # one line per run with both
    store = Store(tmp_path / "journal.sqlite")
    pts, unit = points(store.trend("mill1", 100), "EX0C", "spindle")
    store.close()
    f = fit(pts, unit)
    ref = stats.linregress([p.temperature_c for p in pts], [p.value for p in pts])
    assert f.slope == pytest.approx(ref.slope) and f.slope_std == pytest.approx(ref.stderr)
    assert f.r == pytest.approx(ref.rvalue)
    assert f.slope_u95 == pytest.approx(stats.t.ppf(0.975, 28) * ref.stderr)
    assert f"95 %: ± {f.slope_u95:.3g}, Student's t with 28 dof; 30 runs" in out
    assert abs(f.slope - 1.5) < 2 * f.slope_std
    assert f.r > 0.9 and f.n == 30
    assert (f"EX0C against spindle: r = {f.r:+.2f}, slope {f.slope:+.3g} ± {f.slope_std:.3g} "
            "µm/°C") in out
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and f"wrote {png}" in out
    # the run's temperature is the channel's mean over its poses
    assert sorted(p.temperature_c for p in pts) == pytest.approx(sorted(temps))


def test_no_dependence_gives_a_slope_within_2u_of_zero(tmp_path):
    fill(tmp_path, slope=0.0, seed=4)
    store = Store(tmp_path / "journal.sqlite")
    f = fit(*points(store.trend("mill1", 100), "EX0C", "spindle"))
    store.close()
    assert abs(f.slope) < 2 * f.slope_std and abs(f.r) < 0.5


@pytest.mark.parametrize(("args", "message"), [
    (["--against-temperature", "spindel", "--link", "EX0C"],
     "no temperature channel 'spindel' (configured: spindle)"),
    (["--against-temperature", "spindle", "--link", "EX0Q"], "--link EX0Q: not a location error"),
    (["--against-temperature", "spindle"], "needs --machine and --link"),
])
def test_bad_request_is_one_error_line(tmp_path, capsys, args, message):
    cfg = write_daemon_yaml(tmp_path, extra_machine=CHANNELS)
    code = cli_main(["history", "--config", str(cfg), "--machine", "mill1", *args])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("error: ") and err.count("\n") == 1, err
    assert message in err, err


async def test_hmi_trend_against_a_channel_over_http(tmp_path):
    import aiohttp

    from benchmarks.rigs.daemon_helpers import thesis_rows, thesis_setup
    from daemon.analysis.replay_link import ReplayLink, prepare_from_rows
    from daemon.config import load_daemon_config
    from daemon.service.service import Service

    token = "t0k3n-for-temperature-trend-0123"
    fill(tmp_path, slope=1.5)
    path = write_daemon_yaml(tmp_path, token=token, extra_machine=CHANNELS)
    rows = thesis_rows(thesis_setup())
    svc = Service(load_daemon_config(path), lambda s: ReplayLink(rows, s.machine),
                  prepare=prepare_from_rows(rows))
    await svc.start()
    try:
        async with aiohttp.ClientSession(headers={"Authorization": f"Bearer {token}"}) as http:
            url = svc.hmi_url + "api/machines/mill1/trend?limit=100"
            t = await (await http.get(url)).json()
            assert t["channels"] == ["spindle"] and "against" not in t
            t = await (await http.get(url + "&against=spindle&link=EX0C")).json()
            a = t["against"]
            f = fit(*points(svc.store.trend("mill1", 100), "EX0C", "spindle"))
            assert (a["n"], a["r"], a["slope"], a["slope_std"]) == (30, f.r, f.slope,
                                                                    f.slope_std)
            assert a["unit"] == "µm" and a["slope_unit"] == "µm/°C" and len(a["points"]) == 30
            for q, why in (("&against=spindel&link=EX0C", "'spindel' is not a temperature"),
                           ("&against=spindle&link=EX0Q", "'EX0Q' is not a location error"),
                           ("&against=spindle", "None is not a location error")):
                r = await http.get(url + q)
                assert r.status == 400 and why in await r.text(), q
    finally:
        await svc.stop()
