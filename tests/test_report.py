"""The report: self-contained HTML (embedded PNG plots, no external resource), JSON with the
same numbers as the journal, trend over past runs, escaping of untrusted text."""

from __future__ import annotations

import base64
import json
import re

import pytest

from daemon import pipeline, report
from daemon.judge import judge
from daemon.store import Store
from tests.daemon_helpers import thesis_rows, thesis_setup


def journal_run(store: Store, setup, run_id: str, seed: int, started: float,
                reason: str = "") -> None:
    rows = thesis_rows(setup, seed=seed)
    hits = [pipeline.row_to_hit(r, setup.machine) for r in rows]
    store.new_run(run_id, setup.name, "cnc", plan=setup.plan.name, started_at=started)
    store.journal_hits(run_id, hits)
    a = pipeline.analyse(setup, hits, run_id)
    store.save_centres(run_id, a.centre_rows)
    store.save_analysis(run_id, a.data)
    j = judge(a.data, setup.tolerances)
    store.save_verdict(run_id, j.status, [*j.reasons, reason] if reason else list(j.reasons),
                       [c.as_dict() for c in j.checks], j.summary)
    store.set_state(run_id, "DONE")


@pytest.fixture(scope="module")
def store_with_runs(tmp_path_factory):
    """Two journaled runs and the report of the second (written once for the module)."""
    tmp = tmp_path_factory.mktemp("report")
    setup = thesis_setup()
    s = Store(tmp / "j.sqlite")
    journal_run(s, setup, "R1", 1, 1000.0)
    journal_run(s, setup, "R2", 2, 2000.0, reason="<script>alert(1)</script>")
    paths = report.write_report(s, "R2", tmp / "rep", setup)
    yield s, setup, paths
    s.close()


def test_html_is_self_contained_with_plots_and_escaped(store_with_runs):
    _s, _setup, (html_path, _json_path) = store_with_runs
    html = html_path.read_text()
    # no external resource: every src is a data: URI, no link/script tags
    assert not re.search(r"<(script|link)\b", html)
    srcs = re.findall(r'src="([^"]+)"', html)
    assert len(srcs) == 4 and all(x.startswith("data:image/png;base64,") for x in srcs)
    for x in srcs:
        assert base64.b64decode(x.split(",", 1)[1])[:8] == b"\x89PNG\r\n\x1a\n"
    assert "&lt;script&gt;alert(1)&lt;/script&gt;" in html
    for title in ("Volumetric distortion", "Relocalisation vs local distortion", "Link errors",
                  "Trend over past runs"):
        assert title in html


def test_json_has_the_numbers_of_the_journal(store_with_runs):
    s, _setup, (html_path, json_path) = store_with_runs
    doc = json.loads(json_path.read_text())
    assert doc["run"]["id"] == "R2" and doc["verdict"] == s.verdict("R2")
    assert doc["analysis"] == s.analysis("R2").to_json()
    ex0c = doc["analysis"]["links"]["EX0C"]
    assert f"{ex0c['value']:+.2f}" in html_path.read_text()
    assert [t["run_id"] for t in doc["trend"]] == ["R1", "R2"]
    assert doc["trend"][0]["links"]["EX0C"] == s.analysis("R1").links["EX0C"].value


def test_single_run_has_no_trend_plot_and_run_without_analysis_is_refused(tmp_path):
    setup = thesis_setup()
    s = Store(tmp_path / "j.sqlite")
    journal_run(s, setup, "R1", 1, 1000.0)
    html, _ = report.build(s, "R1", setup.tolerances)
    assert "Trend over past runs" not in html and "Link errors" in html
    s.new_run("R0", setup.name, "cnc")
    with pytest.raises(ValueError, match="R0 has no analysis"):
        report.build(s, "R0", None)
    s.close()


@pytest.mark.parametrize("run_id", ["../evil", "../../x/PWNED", "a.b"])
def test_report_of_a_bad_run_id_is_refused_and_writes_nothing(store_with_runs, tmp_path,
                                                               run_id):
    """A run id journaled before ids were checked (copied here into the journal by SQL) must
    not name a file outside the reports directory."""
    s, setup, _ = store_with_runs
    copy = Store(tmp_path / "copy.sqlite")
    s.db.backup(copy.db)  # a copy: the module's journal stays as it is
    copy.db.execute("INSERT INTO runs SELECT ?, machine, trigger, state, reason, plan, artefact,"
                    " dialect, touch_total, started_at, ended_at, verdict, summary, imported"
                    " FROM runs WHERE id='R2'", (run_id,))
    copy.db.execute("INSERT INTO estimates SELECT ?, analysis FROM estimates WHERE run_id='R2'",
                    (run_id,))
    reports = tmp_path / "a" / "b" / "reports"
    with pytest.raises(ValueError, match="invalid run id"):  # RunIdError
        report.write_report(copy, run_id, reports, setup)
    copy.close()
    written = [p for p in tmp_path.rglob("*") if p.suffix in (".html", ".json")]
    assert written == [], written
