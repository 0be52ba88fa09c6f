"""A map of the linear axes journaled (``rumba map --store``, ``record_map_result``): its
figures, verdict and files' hashes in the journal; ``rumba history`` lists it (kind map) and
exports its map file; the AQDEF export carries its characteristics (read back by an independent
reader); bad input is one line."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from contracts.linear_map import load_map
from daemon.store import map_results
from daemon.store.journal import Store
from tests.aqdef_reader import read_aqdef
from tests.map_result_helpers import journaled_map
from tests.test_map_cli import MACHINE, files, run_cli  # noqa: F401 (files: the fixture)

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def journaled(files, tmp_path_factory):  # noqa: F811
    tmp = tmp_path_factory.mktemp("mapstore")
    cfg, mjson, rep, so = journaled_map(tmp, files[1])
    return tmp, cfg, mjson, rep, so, files[1]


def _one(tmp) -> map_results.MapResult:
    store = Store(tmp / "journal.sqlite")
    try:
        got = map_results.listed(store)
    finally:
        store.close()
    assert len(got) == 1
    return got[0]


def test_the_journal_holds_the_maps_figures_verdict_and_hashes(journaled):
    tmp, _, mjson, rep, so, _ = journaled
    m = _one(tmp)
    doc = load_map(mjson)
    fig = doc.figures.volumetric_max_um
    assert m.machine == "mill1" and m.run_id == "" and m.id.startswith("map-")
    assert f"journaled map {m.id} of mill1" in so
    assert m.volumetric_max_um == pytest.approx(fig.value_um, rel=1e-12)
    assert m.volumetric_max_u_um == pytest.approx(fig.u_um, rel=1e-12)
    assert m.volumetric_rms_um == pytest.approx(doc.figures.volumetric_rms_um, rel=1e-12)
    # judged against the daemon.yaml's volumetric limit (warn 5 µm: the map's max is larger)
    assert fig.value_um > 5 and m.verdict == fig.status == "WARN"
    assert "5 µm" in m.limit_text
    assert m.placements == 2
    assert m.figures["covered_mm"] == {a.axis: a.range_mm for a in doc.basis.axes}
    assert m.figures["unobservable"] == doc.observability.unobservable
    pos = m.figures["positioning_max_um"]
    exx = next(f for f in doc.functions if f.name == "EXX")
    assert pos["EXX"]["value_um"] == pytest.approx(max(abs(v) for v in exx.value))
    assert m.json_sha256 == map_results.sha256_of(mjson)
    assert m.report_html == str((rep / "map.html").resolve())
    assert m.report_sha256 == map_results.sha256_of(rep / "map.html")


def test_history_lists_the_map_with_its_figures_and_verdict(journaled, capsys):
    tmp, cfg, *_ = journaled
    m = _one(tmp)
    code, so, se = run_cli(["history", "--config", str(cfg)])
    assert code == 0, se
    text = " ".join(so.split())
    assert "Map results of the linear axes" in so and m.id in text
    assert f"{m.volumetric_max_um:.1f} ± {m.volumetric_max_u_um:.1f}" in text
    assert f"{m.volumetric_rms_um:.1f}" in text and "WARN" in text


def test_export_of_a_map_writes_its_file_and_refuses_a_changed_one(journaled, tmp_path):
    tmp, cfg, mjson, *_ = journaled
    m = _one(tmp)
    out = tmp_path / "exported.json"
    code, so, se = run_cli(["history", "--config", str(cfg), "--export", m.id,
                            "--json", str(out)])
    assert code == 0, se
    assert f"map {m.id} of mill1" in so
    assert out.read_bytes() == mjson.read_bytes()
    # --csv of a map: it has no touches of its own; says what to do
    code, _, se = run_cli(["history", "--config", str(cfg), "--export", m.id,
                           "--csv", str(tmp_path / "x.csv")])
    assert code == 2 and "--json OUT" in se and "Traceback" not in se
    # a map file changed since it was journaled is refused, never exported as the journaled one
    keep = tmp_path / "keep.json"
    shutil.copy(mjson, keep)
    try:
        d = json.loads(mjson.read_text())
        d["figures"]["volumetric_rms_um"] = 0.001
        mjson.write_text(json.dumps(d))
        code, _so, se = run_cli(["history", "--config", str(cfg), "--export", m.id,
                                "--json", str(tmp_path / "y.json")])
        assert code == 2 and "changed since it was journaled" in se
        assert not (tmp_path / "y.json").exists()
    finally:
        shutil.copy(keep, mjson)


def test_the_aqdef_export_carries_the_map_characteristics(journaled, tmp_path):
    tmp, cfg, _mjson, *_ = journaled
    m = _one(tmp)
    out = tmp_path / "mill1.dfq"
    code, so, se = run_cli(["history", "--config", str(cfg), "--export-aqdef", str(out)])
    assert code == 0, se
    assert "0 runs and 1 map results of mill1" in so
    f = read_aqdef(out)
    by_name = {c["K2001"]: (i, c) for i, c in f.characteristics.items()}
    assert {"MAP_VD_MAX", "MAP_VD_RMS", "MAP_EXX_MAX"} <= set(by_name)
    i, c = by_name["MAP_VD_MAX"]
    # the machine's volumetric limit, [0, fail] (a norm), in µm
    assert (c["K2142"], c["K2110"], c["K2111"]) == ("µm", "0.000", "400.000")
    (rec,) = f.values[i]
    assert float(rec["K0001"]) == pytest.approx(m.volumetric_max_um, abs=5e-4)
    assert rec["K0006"] == m.id and "map; verdict WARN" in rec["K0009"]
    assert f"u {m.volumetric_max_u_um:.3f}" in rec["K0009"]
    i, c = by_name["MAP_VD_RMS"]
    assert "K2111" not in c  # reported, not judged
    assert float(f.values[i][0]["K0001"]) == pytest.approx(m.volumetric_rms_um, abs=5e-4)
    i, _ = by_name["MAP_EXX_MAX"]
    assert float(f.values[i][0]["K0001"]) == pytest.approx(
        m.figures["positioning_max_um"]["EXX"]["value_um"], abs=5e-4)


@pytest.mark.peer
def test_the_aqdef_file_reads_back_in_aqdefreader(journaled, tmp_path):
    reader = ROOT / ".peers" / "aqdef" / "bin" / "python"
    if not reader.exists():
        pytest.skip("aqdefreader peer not installed (bash .ci/install-peers.sh aqdefreader)")
    tmp, cfg, *_ = journaled
    m = _one(tmp)
    out = tmp_path / "peer.dfq"
    assert run_cli(["history", "--config", str(cfg), "--export-aqdef", str(out)])[0] == 0
    read = subprocess.run([str(reader), str(ROOT / "tests" / "peers" / "aqdef_read.py"),
                           str(out)], capture_output=True, text=True, timeout=120, check=True)
    chars = json.loads(read.stdout)  # its own encoding guess: the unit is not compared
    vd = chars["MAP_VD_MAX"]
    assert float(vd["K2111"]) == pytest.approx(400.0)
    assert float(vd["K2110"]) == 0.0
    assert vd["values"] == pytest.approx([m.volumetric_max_um], abs=5e-4)
    assert chars["MAP_VD_RMS"]["values"] == pytest.approx([m.volumetric_rms_um], abs=5e-4)
    assert chars["MAP_EXX_MAX"]["values"] == pytest.approx(
        [m.figures["positioning_max_um"]["EXX"]["value_um"]], abs=5e-4)


def test_record_map_result_for_a_daemon_job_takes_the_runs_id_and_machine(journaled, tmp_path):
    _, _, mjson, rep, *_ = journaled
    store = Store(tmp_path / "j.sqlite")
    try:
        store.new_run("r-map-1", "mill2", "hmi", state="DONE")
        m = map_results.record_map_result(store, "r-map-1", mjson, rep)
        assert (m.id, m.machine, m.run_id) == ("r-map-1", "mill2", "r-map-1")
        again = map_results.record_map_result(store, "r-map-1", mjson, None)  # fitted again
        assert again.report_html == "" and len(map_results.listed(store)) == 1
        assert map_results.last(store, "mill2").id == "r-map-1"
        assert map_results.last(store, "mill1") is None
        with pytest.raises(map_results.MapResultError, match="not 'mill1'"):
            map_results.record_map_result(store, "r-map-1", mjson, machine="mill1")
        with pytest.raises(map_results.StoreError, match="no run 'nope'"):
            map_results.record_map_result(store, "nope", mjson)
        with pytest.raises(map_results.MapResultError, match=r"expected map\.html"):
            map_results.record_map_result(store, "r-map-1", mjson, tmp_path)
        bad = tmp_path / "bad.json"
        bad.write_text('{"schema": "rumba-linear-map/1", "machine": 3}')
        with pytest.raises(map_results.MapResultError, match=r"bad\.json"):
            map_results.record_map_result(store, "r-map-1", bad)
        assert len(map_results.listed(store)) == 1  # nothing journaled by a refusal
    finally:
        store.close()


@pytest.mark.parametrize(("extra", "says"), [
    (["--json", "/nonexistent/x.json", "--store"],
     "--store journals the map in the daemon's journal: give --config"),
    (["--predict", "p.csv", "--out", "o.csv", "--config", "{cfg}", "--store"],
     "--store journals the map file's path and hash: give --json OUT.json and/or --report"),
])
def test_store_without_a_config_or_a_file_is_one_line_before_the_fit(journaled, extra,
                                                                      says):
    _, cfg, *_, out = journaled
    extra = [x.replace("{cfg}", str(cfg)) for x in extra]
    code, _so, se = run_cli(["map", "--machine", str(MACHINE), "--placement", *out[0], *extra])
    assert code == 2 and says in se and "Traceback" not in se


def test_history_refuses_json_for_a_run_and_an_unknown_id(journaled):
    tmp, cfg, *_ = journaled
    store = Store(tmp / "journal.sqlite")
    try:
        store.new_run("r-plain-1", "mill1", "cnc", state="DONE")
    finally:
        store.close()
    for ident, says in (("r-plain-1", "--json OUT exports a map result; r-plain-1 is not one"),
                        ("no-such", "--json OUT exports a map result; no-such is not one")):
        code, _, se = run_cli(["history", "--config", str(cfg), "--export", ident,
                               "--json", "x.json"])
        assert code == 2 and says in se and "Traceback" not in se


def own_journal(tmp, tmp_path, extra: str = ""):
    """The module's daemon.yaml with a journal of this test's own (and ``extra`` lines)."""
    cfg = tmp_path / "daemon.yaml"
    cfg.write_text((tmp / "daemon.yaml").read_text().replace(
        f"store: {{path: {tmp / 'journal.sqlite'}}}",
        f"store: {{path: {tmp_path / 'own.sqlite'}}}\n{extra}"))
    return cfg


def test_a_saved_map_can_be_journaled(journaled, tmp_path):
    tmp, _, mjson, *_ = journaled
    code, so, se = run_cli(["map", "--machine", str(MACHINE), "--map", str(mjson), "--config",
                            str(own_journal(tmp, tmp_path)), "--store"])
    assert code == 0, se
    assert "journaled map map-" in so
    store = Store(tmp_path / "own.sqlite")
    try:
        (m,) = map_results.listed(store)
    finally:
        store.close()
    assert m.report_html == "" and m.json_path == str(mjson.resolve())


def test_runs_and_maps_in_one_aqdef_file_keep_their_own_characteristics(journaled, tmp_path):
    """The runs' characteristics and records are those of a file without maps; the map's
    follow with their own indices (a record never lands on a run's characteristic)."""
    from benchmarks.rigs.daemon_helpers import TOLERANCES
    from daemon.reports.aqdef import aqdef_lines
    from tests.test_aqdef import fill

    tmp = journaled[0]
    m = _one(tmp)
    store = Store(tmp_path / "j.sqlite")
    try:
        fill(store, 3)
        runs = store.trend("mill1")
    finally:
        store.close()
    plain = aqdef_lines("mill1", runs, TOLERANCES)
    both = aqdef_lines("mill1", runs, TOLERANCES, maps=[m])
    out = tmp_path / "both.dfq"
    out.write_bytes(("\r\n".join(both) + "\r\n").encode("cp1252"))
    f = read_aqdef(out)
    n_runs = int(plain[0].split()[1])
    assert int(f.header["K0100"]) == len(f.characteristics) == n_runs + 5
    names = [f.characteristics[i]["K2001"] for i in sorted(f.characteristics)]
    assert names[n_runs:] == ["MAP_VD_MAX", "MAP_VD_RMS", "MAP_EXX_MAX", "MAP_EYY_MAX",
                              "MAP_EZZ_MAX"]
    # every run characteristic: the same three records as without the map
    for i in range(1, n_runs + 1):
        assert [r["K0006"] for r in f.values[i]] == ["r0000", "r0001", "r0002"]
    for i in range(n_runs + 1, n_runs + 6):
        assert [r["K0006"] for r in f.values[i]] == [m.id]
    # the description part of the runs' characteristics unchanged by the map's
    desc = [x for x in plain if x[:2] in ("K1", "K2")]
    assert [x for x in both if x[:2] in ("K1", "K2")][:len(desc)] == desc


def test_the_aqdef_drop_gets_a_map_jobs_map_and_a_stored_map(journaled, tmp_path):
    """aqdef_dir: a map job's run (no daily-check analysis) drops its map's figures; ``rumba
    map --store`` drops the map it journaled."""
    from benchmarks.rigs.daemon_helpers import thesis_setup
    from daemon.service.aqdef_drop import AqdefDrop

    tmp, _, mjson, rep, *_ = journaled
    store = Store(tmp_path / "j.sqlite")
    try:
        store.new_run("JOB-1", "mill1", "hmi", state="DONE")
        map_results.record_map_result(store, "JOB-1", mjson, rep)
        drop = AqdefDrop(tmp_path / "spc", thesis_setup(), store)
        path = drop.drop("JOB-1")
        assert path == tmp_path / "spc" / "mill1_JOB-1.dfq"
        f = read_aqdef(path)
        names = {c["K2001"] for c in f.characteristics.values()}
        assert "MAP_VD_MAX" in names and "VD_MAX" not in names
        store.new_run("JOB-2", "mill1", "hmi", state="ABORTED")
        assert drop.drop("JOB-2") is None  # no verdict, no map: nothing for the SPC chart
    finally:
        store.close()
    spc_cfg = own_journal(tmp, tmp_path, f"aqdef_dir: {tmp_path / 'drop'}")
    code, so, se = run_cli(["map", "--machine", str(MACHINE), "--map", str(mjson), "--config",
                            str(spc_cfg), "--store"])
    assert code == 0, se
    (dfq,) = (tmp_path / "drop").glob("mill1_map-*.dfq")
    assert f"wrote {dfq} (AQDEF)" in so
    assert read_aqdef(dfq).characteristics[1]["K2001"] == "MAP_VD_MAX"


_LEAVES = [("figures", "volumetric_max_um", "value_um"), ("figures", "volumetric_max_um", "u_um"),
           ("figures", "volumetric_max_um", "status"), ("figures", "volumetric_max_um", "limit"),
           ("figures", "volumetric_rms_um"), ("figures", "points"), ("basis", "axes"),
           ("observability", "unobservable"), ("placements",), ("schema",), ("machine",),
           ("functions",), ("fit", "residual_rms_um"), ("holdout",), ("created_utc",)]
_VALUES = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-10**20, 10**20),
                    st.text(max_size=30), st.none(), st.booleans(),
                    st.lists(st.floats(allow_nan=True), max_size=3),
                    st.dictionaries(st.text(max_size=5), st.floats(), max_size=3))


@settings(max_examples=60, deadline=None, suppress_health_check=[
    HealthCheck.function_scoped_fixture])
@given(leaf=st.sampled_from(_LEAVES), value=_VALUES, k=st.integers(0, 17),
       drop=st.booleans())
def test_fuzzed_map_files_are_journaled_or_refused_in_one_line(journaled, tmp_path, leaf, value,
                                                               k, drop):
    """A map file edited by hand (any leaf replaced or removed, NaN / Infinity literals, a
    function's samples cut): journaled with finite figures, or one MapResultError naming the
    file — tracebacks 0, nothing journaled by a refusal."""
    mjson = journaled[2]
    d = json.loads(mjson.read_text())
    node = d
    for key in leaf[:-1]:
        node = node[key]
    if leaf == ("functions",):  # a function's samples cut short
        node = d["functions"][k % len(d["functions"])]
        node["u"] = node["u"][: len(node["u"]) // 2] if drop else node["u"]
        node["value"] = [value if isinstance(value, float) else 1.0] * len(node["value"])
    elif drop:
        node.pop(leaf[-1], None)
    else:
        node[leaf[-1]] = value
    bad = tmp_path / "fuzzed.json"
    bad.write_text(json.dumps(d, allow_nan=True))
    store = Store(tmp_path / "fuzz.sqlite")
    try:
        before = len(map_results.listed(store, limit=10**6))
        try:
            m = map_results.record_map_result(store, None, bad, machine="mill1")
        except map_results.MapResultError as e:
            assert "\n" not in str(e) and "fuzzed.json" in str(e)
            assert len(map_results.listed(store, limit=10**6)) == before
        else:
            assert np.isfinite(m.volumetric_max_um) and np.isfinite(m.volumetric_rms_um)
            assert m.verdict in (None, "PASS", "WARN", "FAIL")
    finally:
        store.close()
