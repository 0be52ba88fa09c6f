"""Writing a report keeps the daemon's log readable: matplotlib's font subsetting
(fontTools, ~200 INFO lines per PDF) says nothing at INFO, while the daemon's own INFO records
still get through."""

from __future__ import annotations

import logging

from benchmarks.rigs.daemon_helpers import thesis_setup
from benchmarks.rigs.report_helpers import journal_run
from daemon.reports import report
from daemon.store.journal import Store


def test_pdf_font_subsetting_is_silent_at_info(tmp_path, caplog):
    setup = thesis_setup()
    s = Store(tmp_path / "j.sqlite")
    a, j = journal_run(s, setup, "R1", 1, 1000.0)
    with caplog.at_level(logging.INFO):  # the root logger at INFO, as the daemon runs
        html, _json = report.write_report(tmp_path / "rep", s.run("R1"), a.data, j,
                                          a.centre_rows, s.trend(setup.name), setup.tolerances)
        logging.getLogger("daemon.run").info("still heard")
    s.close()
    assert report.pdf_path(html).stat().st_size > 10_000  # the fonts were embedded
    assert not [r for r in caplog.records if r.name.startswith("fontTools")]
    assert [r.getMessage() for r in caplog.records if r.name == "daemon.run"] == ["still heard"]
