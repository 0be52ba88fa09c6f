"""The report for people: the PDF for filing (rendered to PNG with poppler's pdftoppm and read
back with pdftotext: A4, three pages, not blank and without blank bands, with the verdict, what
to do and the audit fields), the plain-language next step per verdict, the audit fields from
the setup files and daemon.yaml ("not recorded" when absent), and the plots' axes (a unit on
every axis, no offset notation, limits drawn, pose visits told apart, a reference arrow and
colour legend)."""

from __future__ import annotations

import dataclasses
import json
import re
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from matplotlib import image as mpimg
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.quiver import QuiverKey

from benchmarks.rigs.daemon_helpers import CONFIG, TOLERANCES, thesis_setup, write_daemon_yaml
from benchmarks.rigs.report_helpers import journal_run
from daemon.analysis.judge import Check, Judgement
from daemon.analysis.result import Analysis, Cluster, LinkError
from daemon.analysis.verdict_text import ADVICE, duration_text
from daemon.config import load_daemon_config
from daemon.machines.tolerances import Limit
from daemon.reports import plots as report_plots
from daemon.reports import report
from daemon.reports.pdf import write_pdf
from daemon.store.journal import Store, TrendPoint

AUDIT = report.Audit(machine_serial="DMU65-2019-04417", operator="J. Keller, shift 1",
                     artefact_certificate="DAkkS D-K-15183 #2024-117",
                     artefact_calibrated_on="2024-11-05")


def tool(name: str) -> str:
    exe = shutil.which(name)
    if exe is None:
        pytest.skip(f"{name} not installed (poppler-utils: bash .ci/install-peers.sh chromium)")
    return exe


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Three journaled runs of one machine; the report of the last (with its trend)."""
    tmp = tmp_path_factory.mktemp("pdf")
    setup = thesis_setup()
    s = Store(tmp / "j.sqlite")
    now = time.time()
    for i in range(3):
        a, j = journal_run(s, setup, f"R{i}", i, now - (3 - i) * 86400)
    html, _js = report.write_report(tmp / "rep", s.run("R2"), a.data, j, a.centre_rows,
                                   s.trend(setup.name), setup.tolerances, AUDIT)
    yield s, setup, (a, j), html
    s.close()


def pages(pdf: Path, out: Path, dpi: int = 40) -> list[np.ndarray]:
    subprocess.run([tool("pdftoppm"), "-r", str(dpi), "-png", str(pdf), str(out / "page")],
                   check=True, timeout=60)
    return [mpimg.imread(p) for p in sorted(out.glob("page-*.png"))]


def text_of(pdf: Path) -> str:
    return subprocess.run([tool("pdftotext"), "-layout", str(pdf), "-"], check=True,
                          capture_output=True, text=True, timeout=60).stdout


@pytest.mark.peer
def test_pdf_is_three_a4_pages_not_blank_with_verdict_advice_and_audit(runs, tmp_path):
    _s, _setup, _, html = runs
    pdf = report.pdf_path(html)
    imgs = pages(pdf, tmp_path)
    assert len(imgs) == 3
    for img in imgs:  # A4 at 40 dpi: 8.27 × 11.69 in
        assert img.shape[:2] == (468, 331), img.shape
        ink = (img[..., :3].mean(axis=2) < 0.9).mean()
        assert ink > 0.03, ink  # text and plots, not an empty page
    text = text_of(pdf)
    for expected in ("Machine mill1 — run R2", "PASS", "What to do: " + ADVICE["PASS"][:30],
                     "DMU65-2019-04417", "J. Keller, shift 1", "DAkkS D-K-15183 #2024-117",
                     "2024-11-05", "not recorded (no temperature sensor connected)",
                     "Checks", "EX0C", "page 1 of 3", "page 2 of 3", "page 3 of 3"):
        assert expected in text, expected


def blank_bands_in(img: np.ndarray, dpi: int) -> list[float]:
    """Heights (inches) of the all-white horizontal bands between the first and the last ink
    of a page rendered at ``dpi`` (the footer left out)."""
    ink = (img[..., :3].mean(axis=2) < 0.9).any(axis=1)
    rows = np.flatnonzero(ink[: int(img.shape[0] - 0.4 * dpi)])
    gaps = np.diff(rows) - 1
    return [g / dpi for g in gaps if g > 0]


@pytest.mark.peer
def test_pdf_carries_the_html_sections_without_blank_bands(tmp_path):
    """The PDF has the HTML's setup errors, validation, health, each figure's
    definition, the link errors with plain and controller names, the decision rule, the
    baseline, probe and balls, and the approval block; no page has a blank band of more than
    0.6 in between its text and plots (page 1 put the link plot at the page bottom before)."""
    setup = thesis_setup()
    s = Store(tmp_path / "j.sqlite")
    a, j = journal_run(s, setup, "R0", 0, time.time() - 3600)
    audit = report.audit_of(setup)
    html, _ = report.write_report(tmp_path / "rep", s.run("R0"), a.data, j, a.centre_rows,
                                  s.trend(setup.name), setup.tolerances, audit)
    s.close()
    pdf = report.pdf_path(html)
    text = " ".join(text_of(pdf).split())
    for expected in ("Setup errors", "ball B1", "Probe and ball health", "Figures and their "
                     "definitions", "max volumetric distortion (probed poses)",
                     "EX0C — X offset of the C axis line, Siemens $TC_CARR15[1] (c-x)",
                     "ISO 14253-1 decision rule", "Drift baseline", "none set: drift not "
                     "checked", "Probe", "stylus diameter", "Balls", "Prepared by",
                     "Checked by", "Approved by"):
        assert expected in text, expected
    html_text = " ".join(html.read_text().split())
    for expected in ("EX0C — X offset of the C axis line, Siemens $TC_CARR15[1] (c-x)",
                     "ISO 14253-1 decision rule", "Approved by", "Setup errors"):
        assert expected in html_text, expected
    for k, img in enumerate(pages(pdf, tmp_path, dpi=50)):
        bands = blank_bands_in(img, 50)
        assert max(bands, default=0.0) < 0.6, (k + 1, sorted(bands)[-3:])


@pytest.mark.peer
def test_many_checks_stay_on_three_pages(runs, tmp_path):
    """A judgement with 80 checks (a long machine chain, drift checks): page 1 lists what fits,
    the not-passed first, counts the rest, and the PDF is still three pages."""
    s, _setup, (a, j), _ = runs
    many = (*(Check(f"quantity {k}", float(k), 0.1, "µm", "PASS", "warn 1 / fail 2")
              for k in range(80)), Check("EX0C drift", 25.0, 0.2, "µm", "FAIL", "drift > 20"))
    judged = dataclasses.replace(j, status="FAIL", checks=many)
    _, doc = report.build(s.run("R2"), bare(a.data), judged, a.centre_rows, [], None)
    pdf = write_pdf(tmp_path / "many.pdf", s.run("R2"), a.data, doc, report.Audit(), {})
    assert len(pages(pdf, tmp_path)) == 3
    text = text_of(pdf)
    assert re.search(r"… \d+ more checks, all PASS, in the HTML and JSON report", text)
    assert "EX0C drift" in text  # the failed one is listed, whatever its place


def test_html_and_json_carry_what_to_do_audit_and_pdf(runs):
    _s, _setup, _, html_path = runs
    html = html_path.read_text()
    assert "What to do:</b> " + ADVICE["PASS"] in html
    assert "@page{size:A4" in html and "@media print" in html  # prints as A4 too
    assert '<a href="R2.pdf">R2.pdf</a>' in html
    for value in ("DMU65-2019-04417", "J. Keller, shift 1", "DAkkS D-K-15183 #2024-117"):
        assert value in html
    doc = json.loads(html_path.with_suffix(".json").read_text())
    assert doc["what_to_do"] == ADVICE["PASS"]
    assert doc["audit"]["machine_serial"] == "DMU65-2019-04417"
    assert doc["audit"]["temperature_c"] is None
    assert doc["files"]["pdf"] == "R2.pdf"


def bare(a: Analysis) -> Analysis:
    """The analysis without what the plots draw (these tests read text, not pictures)."""
    return dataclasses.replace(a, volumetric=(), cluster=(), links={})


@pytest.mark.parametrize("status", ["PASS", "WARN", "FAIL", "ERROR"])
def test_every_verdict_says_what_to_do(runs, status):
    s, setup, (a, j), _ = runs
    judged = Judgement(status, (f"a reason for {status}",), j.checks, f"{status}: summary")
    html, doc = report.build(s.run("R2"), bare(a.data), judged, a.centre_rows, [],
                             setup.tolerances)
    assert doc["what_to_do"] == ADVICE[status]
    assert f"What to do:</b> {ADVICE[status]}" in html
    assert len({*ADVICE.values()}) == 4  # four different sentences


def test_no_audit_given_is_not_recorded(runs):
    s, setup, (a, j), _ = runs
    html, doc = report.build(s.run("R2"), bare(a.data), j, a.centre_rows, [],
                             setup.tolerances)
    assert html.count("not recorded") >= 4  # serial, operator, calibration, temperature
    assert doc["audit"] == dataclasses.asdict(report.Audit())


def test_audit_fields_come_from_the_setup_files_and_daemon_yaml(tmp_path):
    machine = (CONFIG / "machines/thesis_wcbxfzyt.yaml").read_text() + \
        "serial: 'HMC500 #2019-0417'\nprobe: {model: 'Renishaw OMP40-2', serial: 'P-1234', " \
        "qualified_on: 2026-01-12, qualified_by: 'A. Berg'}\n"
    artefact = (CONFIG / "artefacts/thesis_4ball.yaml").read_text() + \
        "calibration: {certificate: 'DKD-K-15183 2024-117', date: 2024-11-05}\n"
    (tmp_path / "m.yaml").write_text(machine)
    (tmp_path / "a.yaml").write_text(artefact)
    path = write_daemon_yaml(tmp_path, extra_machine="    operator: 'J. Keller (shift 1)'")
    text = path.read_text().replace(str(CONFIG / "machines/thesis_wcbxfzyt.yaml"),
                                    str(tmp_path / "m.yaml"))
    path.write_text(text.replace(str(CONFIG / "artefacts/thesis_4ball.yaml"),
                                 str(tmp_path / "a.yaml")))
    from contracts.yaml_files import ConfigError

    audit = report.audit_of(load_daemon_config(path).machines["mill1"])
    assert dataclasses.astuple(audit)[:4] == ("HMC500 #2019-0417", "J. Keller (shift 1)",
                                              "DKD-K-15183 2024-117", "2024-11-05")
    # the probe's qualification, the balls' diameters, the decision rule
    assert audit.probe == ("Renishaw OMP40-2 serial P-1234, stylus diameter 6 mm (plan "
                           "thesis-ch3-7poses), qualified on 2026-01-12 by A. Berg")
    assert audit.balls == "B1 ⌀25.4 mm, B2 ⌀25.4 mm, B3 ⌀25.4 mm, B4 ⌀25.4 mm"
    assert "ISO 14253-1" in (audit.decision_rule or "") and audit.baseline is None
    assert audit.link_names["EX0C"].startswith("EX0C — X offset of the C axis line, Siemens ")
    (tmp_path / "m.yaml").write_text(machine.replace("2026-01-12", "2999-01-01"))
    with pytest.raises(ConfigError, match=r"m\.yaml: probe\.qualified_on: .*in the future"):
        load_daemon_config(path)
    (tmp_path / "m.yaml").write_text(machine.replace("qualified_by", "qualified_at"))
    with pytest.raises(ConfigError, match=r"m\.yaml: probe\.qualified_at: unknown key"):
        load_daemon_config(path)
    (tmp_path / "m.yaml").write_text(machine)
    (tmp_path / "a.yaml").write_text(artefact.replace("date: 2024-11-05",
                                                      "date: 2024-11-05, by: me"))
    with pytest.raises(ConfigError, match=r"a\.yaml: calibration\.by: unknown key"):
        load_daemon_config(path)
    (tmp_path / "a.yaml").write_text(artefact)
    (tmp_path / "m.yaml").write_text(machine.replace("'HMC500 #2019-0417'", '"x\\ny"'))
    with pytest.raises(ConfigError, match=r"m\.yaml: serial: String should match pattern"):
        load_daemon_config(path)


# --------------------------------------------------------------------------------- the plots


def _trend(values_um: list[float]) -> list[TrendPoint]:
    """Runs with the given EX0C (µm) and an EB0Z (µrad), no distortion."""
    return [TrendPoint(f"R{k}", 1e9 + 86400 * k, "PASS", Analysis(links={
        "EX0C": LinkError(v, 0.2, "um"), "EB0Z": LinkError(-12.0 + k, 1.5, "urad")}))
        for k, v in enumerate(values_um)]


def test_trend_has_one_unit_axis_per_link_with_limits_and_no_offset():
    fig = Figure(figsize=(7.2, 6), layout="constrained")
    tol = dataclasses.replace(TOLERANCES, links={"EX0C": Limit(warn=150, fail=300)})
    assert report_plots.draw_trend(fig, _trend([110.41, 110.50, 110.47]), tol)
    FigureCanvasAgg(fig).draw()
    axes = {ax.get_title(loc="left"): ax for ax in fig.axes if ax.get_visible()}
    assert set(axes) == {"EB0Z", "EX0C"}  # links only: no distortion in these analyses
    assert axes["EX0C"].get_ylabel() == "µm" and axes["EB0Z"].get_ylabel() == "µrad"
    for ax in axes.values():
        assert ax.yaxis.get_major_formatter().get_offset() == ""  # no "+1.104e2"
    lo, hi = axes["EX0C"].get_ylim()
    assert lo <= -300 and hi >= 300  # the fail limit is on the axis, drawn ±
    ys = sorted(round(line.get_ydata()[0]) for line in axes["EX0C"].get_lines()
                if line.get_linestyle() in ("--", "-") and len(set(line.get_ydata())) == 1)
    assert {-300, -150, 150, 300} <= set(ys), ys
    assert axes["EX0C"].get_title(loc="right").replace("−", "-") == "+110.5 µm\nΔ-0.0"


def test_cluster_plot_separates_units_and_pose_visits():
    cl = (Cluster(0, 0, 0.0, 0.0, (100.0, 3.0, 1.0), (40.0, 5.0, 1.0), {"B1": (1.0, 1.0, 0)}),
          Cluster(1, 0, 45.0, 0.0, (101.0, 3.0, 1.0), (50.0, 5.0, 1.0), {"B1": (1.0, 1.0, 0)}),
          Cluster(0, 1, 0.0, 0.0, (100.5, 3.0, 1.0), (41.0, 5.0, 1.0), {"B1": (1.0, 1.0, 0)}))
    fig = Figure(figsize=(7.2, 3.6), layout="constrained")
    assert report_plots.draw_cluster(fig, Analysis(cluster=cl))
    top, bottom = fig.axes
    assert (top.get_ylabel(), bottom.get_ylabel()) == ("µm", "µrad")
    labels = [t.get_text() for t in bottom.get_xticklabels()]
    assert labels == ["0 #1\nB0\nC0", "1\nB45\nC0", "0 #2\nB0\nC0"]
    for ax in (top, bottom):  # legends beside the bars, not on them
        assert ax.get_legend().get_bbox_to_anchor().x0 >= ax.bbox.x1 - 1


def test_distortion_plot_has_a_reference_arrow_and_a_colour_legend(runs):
    _s, _setup, (a, _j), _ = runs
    centres = {(c[0], c[1]): c[4:7] for c in a.centre_rows}
    fig = Figure(figsize=(7.2, 6.4), layout="constrained")
    assert report_plots.draw_distortion(fig, a.data, centres)
    keys = [c for ax in fig.axes for c in ax.get_children() if isinstance(c, QuiverKey)]
    assert len(keys) == 3 and all(k.text.get_text().endswith(" µm") for k in keys)
    legend = [t.get_text() for t in fig.legends[0].get_texts()]
    assert legend[0] == "pose 0 (B0 C0)" and len(legend) == len({v.pose for v in
                                                                   a.data.volumetric})


def test_durations_read_the_same_everywhere():
    assert [duration_text(s) for s in (7.1, 119, 228, 7199, 18000)] == [
        "7 s", "119 s", "3.8 min", "120.0 min", "5.0 h"]


def test_pdf_embeds_each_font_once_and_fonttools_stays_quiet(runs, caplog):
    """"—", "•", "→" and ligatures ("fi") opened a second subset of DejaVu Sans and
    DejaVu Sans Bold (4 embedded fonts for 2 faces); one subset each, and fontTools' table-
    pruning chatter is not in the log."""
    _s, _setup, (a, _j), html = runs
    pdf = report.pdf_path(html).read_bytes()
    # a subset is named by its prefix (ABCDEF+DejaVuSans: Type0 font and its CID font)
    subsets = set(re.findall(rb"/BaseFont /([A-Z]{6}\+[A-Za-z0-9-]+)", pdf))
    assert sorted(f.split(b"+")[1] for f in subsets) == [b"DejaVuSans", b"DejaVuSans-Bold"]
    import logging
    with caplog.at_level(logging.DEBUG):
        write_pdf(report.pdf_path(html).with_name("again.pdf"), _s.run("R2"), a.data,
                  json.loads(Path(html).with_suffix(".json").read_text()), AUDIT, {})
    assert not [r for r in caplog.records if r.name.startswith("fontTools")
                and r.levelno < logging.WARNING]
