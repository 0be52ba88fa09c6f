"""SPC export: ``rumba history --export-aqdef`` read back by an independent AQDEF
reader (tests/aqdef_reader.py): part, characteristics with limits and units, one value record
per run and characteristic; a year of daily runs; no field injection through names."""

from __future__ import annotations

import time

import pytest

from benchmarks.rigs.daemon_helpers import TOLERANCES, write_daemon_yaml
from daemon.analysis.result import Analysis, LinkError, VolumetricPoint
from daemon.cli.main import main as cli_main
from daemon.reports.aqdef import VOLUMETRIC, write_aqdef
from daemon.store.journal import Store, TrendPoint
from tests.aqdef_reader import read_aqdef

LINKS = {"EX0C": "um", "EY0C": "um", "EA0C": "urad", "EB0C": "urad",
         "EX0B": "um", "EZ0B": "um", "EA0B": "urad", "EC0B": "urad"}
T0 = time.mktime((2026, 1, 1, 6, 30, 0, 0, 0, -1))


def analysis(k: int) -> Analysis:
    links = {n: LinkError(value=round(0.5 * k % 37 - 18 + i, 3), std=0.1 + 0.01 * i, unit=u)
             for i, (n, u) in enumerate(LINKS.items())}
    vol = (VolumetricPoint(pose=0, ball="A", error_um=(3.0, 4.0, 0.0 + k % 5),
                           error_after_links_um=(0.3, 0.4, 0.0)),)
    return Analysis(machine="thesis", links=links, volumetric=vol)


def fill(store: Store, n: int) -> None:
    with store.transaction():
        for k in range(n):
            rid = f"r{k:04d}"
            store.new_run(rid, "mill1", "cnc", started_at=T0 + 86400 * k, state="DONE")
            store.save_analysis(rid, analysis(k))
            store.save_verdict(rid, "FAIL" if k % 50 == 7 else "PASS", [], [], "")


def test_a_year_of_daily_runs_round_trips(tmp_path, capsys):
    cfg = write_daemon_yaml(tmp_path)
    store = Store(tmp_path / "journal.sqlite")
    fill(store, 365)
    store.close()
    out = tmp_path / "mill1.dfq"
    code = cli_main(["history", "--config", str(cfg), "--export-aqdef", str(out)])
    printed = capsys.readouterr().out
    assert code == 0 and f"wrote {out}: 365 runs of mill1" in printed
    f = read_aqdef(out)
    assert f.header["K1001"] == "mill1"
    names = [c["K2001"] for _, c in sorted(f.characteristics.items())]
    assert names == [*sorted(LINKS), *VOLUMETRIC]
    assert f.header["K0100"] == "10"
    by_name = {c["K2001"]: (i, c) for i, c in f.characteristics.items()}
    # limits: the configured fail limits, symmetric for links, [0, fail] for the norm
    i, c = by_name["EA0C"]
    assert (c["K2142"], c["K2101"], c["K2110"], c["K2111"]) == ("µrad", "0.000", "-80.000",
                                                                "80.000")
    i, c = by_name["EX0C"]
    assert (c["K2142"], c["K2110"], c["K2111"]) == ("µm", "-300.000", "300.000")
    i, c = by_name[VOLUMETRIC[0]]
    assert (c["K2110"], c["K2111"]) == ("0.000", "400.000")
    assert "K2110" not in by_name[VOLUMETRIC[1]][1]  # no limit configured: none written
    # the report's names of the two figures, not the export's own wording
    assert c["K2002"] == "max volumetric distortion (probed poses)"
    assert by_name[VOLUMETRIC[1]][1]["K2002"] == ("max residual after the link errors "
                                                  "(probed poses)")
    for i in f.characteristics:
        assert len(f.values[i]) == 365
    # every record: value, date/time, run id, machine, in run order
    i, _ = by_name["EB0C"]
    for k in (0, 1, 200, 364):
        rec = f.values[i][k]
        want = analysis(k).links["EB0C"]
        assert float(rec["K0001"]) == pytest.approx(want.value, abs=5e-4)
        assert rec["K0006"] == f"r{k:04d}" and rec["K0010"] == "mill1"
        assert rec["K0004"] == time.strftime("%d.%m.%Y/%H:%M:%S",
                                             time.localtime(T0 + 86400 * k))
        assert f"u {want.std:.3f} µrad" in rec["K0009"]
    i, _ = by_name[VOLUMETRIC[0]]
    assert float(f.values[i][3]["K0001"]) == pytest.approx(34 ** 0.5, abs=5e-4)  # |(3, 4, 3)|
    assert f.values[i][57]["K0009"].startswith("verdict FAIL")


def test_a_link_missing_in_one_run_leaves_out_only_its_record(tmp_path):
    a0, a1 = analysis(0), analysis(1)
    links = dict(a1.links)
    del links["EZ0B"]
    runs = [TrendPoint("a", T0, "PASS", a0),
            TrendPoint("b", T0 + 60, "PASS", Analysis(links=links, volumetric=a1.volumetric))]
    out = tmp_path / "x.dfq"
    write_aqdef(out, "mill1", runs, TOLERANCES)
    f = read_aqdef(out)
    idx = {c["K2001"]: i for i, c in f.characteristics.items()}
    assert [r["K0006"] for r in f.values[idx["EZ0B"]]] == ["a"]
    assert [r["K0006"] for r in f.values[idx["EX0C"]]] == ["a", "b"]


@pytest.mark.parametrize("evil", ["mill\r\nK0001/1 999", "mill\nK2111/1 1e9", "a\x0fb\x14c",
                                  "K0100 99", "mill ☃ 1"])
def test_names_cannot_inject_fields(tmp_path, evil):
    out = tmp_path / "x.dfq"
    write_aqdef(out, evil, [TrendPoint("a", T0, "PASS", analysis(0))], TOLERANCES,
                operator=evil, artefact=evil)
    f = read_aqdef(out)  # would fail on a bare line break or a line that is not a K-field
    assert f.header["K0100"] == "10"
    assert f.keys.count("K0001") == 10 and f.keys.count("K2111") == 9
    assert all(len(v) == 1 for v in f.values.values())
    rec = f.values[1][0]
    want = "".join(" " if ord(ch) < 32 else ch for ch in evil).strip().replace("☃", "?")
    assert rec["K0008"] == rec["K0010"] == want and f.header["K1001"] == want[:30]


def test_two_machines_need_a_machine_name(tmp_path, capsys):
    extra = """  - name: mill2
    machine: {m}
    artefact: {a}
    plan: {p}
    dialect: fanuc
    link: {{transport: opcua, url: 'opc.tcp://127.0.0.1:4841', security: none}}
"""
    from benchmarks.rigs.daemon_helpers import CONFIG
    cfg = write_daemon_yaml(tmp_path, extra_machine=extra.format(
        m=CONFIG / "machines/thesis_wcbxfzyt.yaml", a=CONFIG / "artefacts/thesis_4ball.yaml",
        p=CONFIG / "plans/thesis_ch3_7poses.yaml"))
    code = cli_main(["history", "--config", str(cfg), "--export-aqdef",
                     str(tmp_path / "x.dfq")])
    err = capsys.readouterr().err
    assert code == 2 and "--export-aqdef: name the machine with --machine" in err
    assert not (tmp_path / "x.dfq").exists()


def _status(state: str, run_id: str | None) -> dict:
    return {"state": state, "run_id": run_id}


def test_the_drop_writes_one_file_per_judged_run_and_never_fails_a_run(tmp_path, caplog):
    from benchmarks.rigs.daemon_helpers import thesis_setup
    from daemon.service.aqdef_drop import AqdefDrop

    store = Store(tmp_path / "journal.sqlite")
    fill(store, 2)
    store.new_run("stopped", "mill1", "hmi", started_at=T0 + 86400 * 5)
    store.set_state("stopped", "ABORTED", "stopped at the HMI")
    drop = AqdefDrop(tmp_path / "spc", thesis_setup(), store)
    for rid in ("r0001", "stopped"):
        drop.on_status(_status("IDLE", None))
        drop.on_status(_status("CAPTURE", rid))
        drop.on_status(_status("IDLE" if rid != "stopped" else "ABORTED", rid))
    assert drop.written == [tmp_path / "spc" / "mill1_r0001.dfq"]  # the aborted run: no file
    f = read_aqdef(drop.written[0])
    assert {v[0]["K0006"] for v in f.values.values()} == {"r0001"}
    assert all(len(v) == 1 for v in f.values.values())
    # a drop folder that cannot be written: logged, the session's listener returns normally
    blocked = AqdefDrop(tmp_path / "spc" / "mill1_r0001.dfq" / "x", thesis_setup(), store)
    blocked.on_status(_status("CAPTURE", "r0000"))
    blocked.on_status(_status("IDLE", "r0000"))
    assert blocked.written == [] and "AQDEF file of run r0000 not written" in caplog.text
    store.close()
