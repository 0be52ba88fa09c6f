"""The report: self-contained HTML (embedded PNG plots, no external resource), JSON with the
same numbers as the journal, trend over past runs, escaping of untrusted text. The report
renders what it is given (run record, analysis, judgement, centres, trend): it never reads
the journal, so these tests journal the runs the way the session does and hand the report
what the session holds."""

from __future__ import annotations

import base64
import dataclasses
import json
import re
from pathlib import Path

import pytest

from benchmarks.rigs.daemon_helpers import thesis_setup
from benchmarks.rigs.report_helpers import journal_run
from daemon.analysis import pipeline
from daemon.analysis.judge import Judgement
from daemon.reports import report
from daemon.store.journal import Store


def render(store: Store, setup, run_id: str, a: pipeline.RunAnalysis, j: Judgement,
           reports: Path) -> tuple[Path, Path]:
    """The session's report step: run record and trend read by the caller, not the report."""
    return report.write_report(reports, store.run(run_id), a.data, j, a.centre_rows,
                               store.trend(setup.name), setup.tolerances)


@pytest.fixture(scope="module")
def store_with_runs(tmp_path_factory):
    """Two journaled runs and the report of the second (written once for the module)."""
    tmp = tmp_path_factory.mktemp("report")
    setup = thesis_setup()
    s = Store(tmp / "j.sqlite")
    journal_run(s, setup, "R1", 1, 1000.0)
    a, j = journal_run(s, setup, "R2", 2, 2000.0, reason="<script>alert(1)</script>")
    paths = render(s, setup, "R2", a, j, tmp / "rep")
    yield s, setup, paths, (a, j)
    s.close()


def test_html_is_self_contained_with_plots_and_escaped(store_with_runs):
    _s, _setup, (html_path, _json_path), _ = store_with_runs
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
    s, _setup, (html_path, json_path), _ = store_with_runs
    doc = json.loads(json_path.read_text())
    assert doc["run"]["id"] == "R2" and doc["verdict"] == s.verdict("R2")
    assert doc["analysis"] == s.analysis("R2").to_json()
    ex0c = doc["analysis"]["links"]["EX0C"]
    assert f"{ex0c['value']:+.2f}" in html_path.read_text()
    assert [t["run_id"] for t in doc["trend"]] == ["R1", "R2"]
    assert doc["trend"][0]["links"]["EX0C"] == s.analysis("R1").links["EX0C"].value


def test_single_run_has_no_trend_plot_and_no_judgement_shows_the_run_state(tmp_path):
    setup = thesis_setup()
    s = Store(tmp_path / "j.sqlite")
    a, j = journal_run(s, setup, "R1", 1, 1000.0)
    run, trend = s.run("R1"), s.trend(setup.name)
    html, doc = report.build(run, a.data, j, a.centre_rows, trend, setup.tolerances)
    assert "Trend over past runs" not in html and "Link errors" in html
    html, doc = report.build(run, a.data, None, a.centre_rows, [], None)
    assert doc["verdict"] is None and '<span class="badge">DONE</span>' in html
    s.close()


@pytest.mark.parametrize("run_id", ["../evil", "../../x/PWNED", "a.b"])
def test_report_of_a_bad_run_id_is_refused_and_writes_nothing(store_with_runs, tmp_path,
                                                               run_id):
    """A run id journaled before ids were checked must not name a file outside the reports
    directory."""
    s, setup, _, (a, j) = store_with_runs
    run = dataclasses.replace(s.run("R2"), id=run_id)
    reports = tmp_path / "a" / "b" / "reports"
    with pytest.raises(ValueError, match="invalid run id"):  # RunIdError
        report.write_report(reports, run, a.data, j, a.centre_rows, s.trend(setup.name),
                            setup.tolerances)
    written = [p for p in tmp_path.rglob("*") if p.suffix in (".html", ".json")]
    assert written == [], written
