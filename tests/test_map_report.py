"""`rumba map --report DIR`: the map section as HTML, PDF and JSON — every observable motion
error shown with its size, the unobservable ones marked (never drawn as a curve), the figures
table equal to the JSON's numbers, a real PDF, the slices' arrow scale stated as drawn; a bad
report path is one error line and exit 2 before any fit runs."""

from __future__ import annotations

import json
import re
from html.parser import HTMLParser

import numpy as np
import pytest
from matplotlib.figure import Figure

from contracts.linear_map import load_map, map_model
from contracts.setup_files import load_machine
from tests.test_map_cli import MACHINE, files, run_cli  # noqa: F401 (files: the fixture)


@pytest.fixture(scope="module")
def report(files):  # noqa: F811
    """The report of the fixture's two placements (fitted again, with --report and --json)."""
    tmp, out, _ = files
    code, so, se = run_cli(["map", "--machine", str(MACHINE), "--placement", *out[0],
                            "--placement", *out[1], "--max-degree", "2", "--limit-um", "10,30",
                            "--json", str(tmp / "r.json"), "--report", str(tmp / "rep")])
    assert code == 0, se
    assert "wrote the map report" in so
    return tmp / "rep", load_map(tmp / "r.json"), json.loads((tmp / "r.json").read_text())


class _Rows(HTMLParser):
    """Table rows of the HTML: (table class, row id, row class, [cell texts])."""

    def __init__(self) -> None:
        super().__init__()
        self.rows: list[tuple[str, str, str, list[str]]] = []
        self.table, self.cell = "", None
        self.tr: tuple[str, str] | None = None
        self.cells: list[str] = []

    def handle_starttag(self, tag: str, attrs: list) -> None:
        a = dict(attrs)
        if tag == "table":
            self.table = a.get("class") or ""
        elif tag == "tr":
            self.tr, self.cells = (a.get("id") or "", a.get("class") or ""), []
        elif tag in ("td", "th"):
            self.cell = ""

    def handle_data(self, data: str) -> None:
        if self.cell is not None:
            self.cell += data

    def handle_endtag(self, tag: str) -> None:
        if tag in ("td", "th") and self.cell is not None:
            self.cells.append(" ".join(self.cell.split()))
            self.cell = None
        elif tag == "tr" and self.tr is not None:
            self.rows.append((self.table, *self.tr, self.cells))
            self.tr = None


def _rows(html: str, table: str) -> list[tuple[str, str, list[str]]]:
    p = _Rows()
    p.feed(html)
    return [(i, c, cells) for t, i, c, cells in p.rows if t == table]


def test_the_html_shows_every_observable_function_and_marks_the_unobservable(report):
    rep, doc, _ = report
    html = (rep / "map.html").read_text(encoding="utf-8")
    rows = {i: (c, cells) for i, c, cells in _rows(html, "functions") if i}
    assert set(rows) == {f.name for f in doc.functions} and len(rows) == 18
    stmt = doc.observability.unobservable
    gone = {f.name for f in doc.functions if not f.terms}
    assert gone and gone <= set(stmt)  # the fixture's stylus: Y's and Z's tilts held by Y, Z
    for f in doc.functions:
        cls, cells = rows[f.name]
        if f.name in gone:
            assert cls == "none" and cells[1] == "not observable" and cells[2] == "—", cells
        else:
            assert cls in ("observable", "partly") and "not observable" not in cells[1]
            assert float(cells[2]) == pytest.approx(max(abs(v) for v in f.value), abs=0.006)
            k = int(np.argmax(np.abs(f.value)))
            assert float(cells[3]) == pytest.approx(f.u[k], abs=0.006)
            assert cells[4] == ("µrad" if f.unit == "urad" else "µm")
            held = [t for t in f.absorbed if t in stmt]
            assert (cls == "partly") == bool(held), (f.name, cls, held)
    words = html.split('id="not-observable"')[1].split("</ul>")[0]
    for name in gone:
        assert name in words
    assert "the map refuses to predict there" in words
    assert html.count("data:image/png;base64,") == 3


def test_an_unobservable_function_is_never_drawn_as_a_curve(report):
    """The functions plot: a curve and a 2u band for what the data determine, a hatched
    'not observable' panel with no curve for what they do not."""
    from daemon.reports.map_plots import draw_functions

    doc = report[1]
    fig = Figure(figsize=(7.2, 9.6))
    assert draw_functions(fig, doc)
    panels = {ax.get_title(loc="left").split(":")[0]: ax for ax in fig.axes}
    for f in doc.functions:
        ax = panels[f.name]
        curves = [ln for ln in ax.get_lines() if len(ln.get_xdata()) == len(f.x_mm)]
        texts = [t.get_text() for t in ax.texts]
        if f.terms:
            assert len(curves) == 1 and "not observable" not in texts
            np.testing.assert_allclose(curves[0].get_ydata(), f.value)
            band = ax.collections[0].get_paths()[0].vertices[:, 1]
            span = np.asarray(f.value) + 2 * np.asarray(f.u)
            assert band.max() == pytest.approx(span.max(), abs=1e-9)
        else:
            assert curves == [] and texts == ["not observable"]


def test_the_figure_table_agrees_with_the_json(report):
    rep, _, raw = report
    html = (rep / "map.html").read_text(encoding="utf-8")
    rows = {cells[0]: cells for _, _, cells in _rows(html, "map-figures")[1:]}
    fig = raw["figures"]
    mx = rows["Volumetric error, max"]
    value, u = (float(x) for x in re.fullmatch(r"([\d.]+) µm ± ([\d.]+) µm \(u, k=1\)",
                                                mx[1]).groups())
    assert value == pytest.approx(fig["volumetric_max_um"]["value_um"], abs=0.006)
    assert u == pytest.approx(fig["volumetric_max_um"]["u_um"], abs=0.006)
    assert mx[2] == fig["volumetric_max_um"]["status"] in ("PASS", "WARN", "FAIL")
    assert fig["volumetric_max_um"]["limit"] in mx[3]
    rms = rows["Volumetric error, RMS"]
    assert float(rms[1].removesuffix(" µm")) == pytest.approx(fig["volumetric_rms_um"],
                                                               abs=0.006)
    assert json.loads((rep / "map.json").read_text()) == raw  # the report's JSON is the map


def test_the_pdf_is_a_pdf_of_four_pages_with_the_map_section(report):
    rep, doc, _ = report
    pdf = (rep / "map.pdf").read_bytes()
    assert pdf.startswith(b"%PDF-") and pdf.rstrip().endswith(b"%%EOF")
    assert len(re.findall(rb"/Type /Page\b", pdf)) == 4
    assert b"rumba-cnc map of the linear axes: machine " + doc.machine["name"].encode() in pdf


def test_the_slices_state_the_arrow_scale_they_draw(report):
    from daemon.reports.map_plots import draw_slices
    from daemon.reports.map_report import slice_fields

    doc = report[1]
    model = map_model(load_machine(MACHINE)[0], doc)
    sl = slice_fields(doc, model, n=5)
    assert [s.name for s in sl] == ["XY", "XZ", "YZ"]
    box = {a.axis: a.range_mm for a in doc.basis.axes}
    for s in sl:  # each slice through the middle of the covered box, spanning its section
        assert s.at_mm == pytest.approx(sum(box["XYZ"[s.k]]) / 2)
        assert s.points_mm[:, s.i].min() == pytest.approx(box["XYZ"[s.i]][0])
    fig = Figure(figsize=(7.2, 6.0))
    assert draw_slices(fig, sl)
    said = next(t.get_text() for ax in fig.axes for t in ax.texts if "1 µm ≙" in t.get_text())
    mm_per_um = float(re.search(r"1 µm ≙ ([\d.]+) mm", said).group(1))
    from matplotlib.quiver import Quiver

    for ax, s in zip([a for a in fig.axes if a.collections], sl, strict=False):
        q = next(c for c in ax.collections if isinstance(c, Quiver))
        np.testing.assert_allclose(q.U, s.error_um[:, s.i] * mm_per_um, rtol=0.01, atol=1e-3)


@pytest.mark.parametrize("where", ["file", "under_file"])
def test_a_bad_report_path_is_one_line_and_exit_2_before_the_fit(files, tmp_path,  # noqa: F811
                                                                   where):
    _, out, _ = files
    (tmp_path / "f").write_text("a file, not a directory")
    target = tmp_path / "f" if where == "file" else tmp_path / "f" / "sub"
    code, _, se = run_cli(["map", "--machine", str(MACHINE), "--placement", "missing.csv",
                            out[0][1], "--report", str(target)])
    assert code == 2 and se.startswith(f"error: --report {target}: cannot write") and \
        se.count("\n") == 1, se
    assert "missing.csv" not in se  # refused before the logs are read or the fit runs


def test_a_saved_map_needs_something_to_do():
    code, _, se = run_cli(["map", "--machine", str(MACHINE), "--map", "m.json"])
    assert code == 2 and "--report DIR" in se and se.count("\n") == 1, se


def test_a_saved_map_gives_the_same_figures(report, files, tmp_path):  # noqa: F811
    rep = report[0]
    tmp = files[0]
    code, _, se = run_cli(["map", "--machine", str(MACHINE), "--map", str(tmp / "r.json"),
                           "--report", str(tmp_path / "again")])
    assert code == 0, se
    a = _rows((rep / "map.html").read_text(encoding="utf-8"), "map-figures")
    b = _rows((tmp_path / "again" / "map.html").read_text(encoding="utf-8"), "map-figures")
    assert a == b and len(a) == 3


def test_a_map_without_a_limit_is_reported_not_judged(report, files, tmp_path):  # noqa: F811
    """No --limit-um / --config: the badge and the table say so, no PASS is invented."""
    raw = json.loads((files[0] / "r.json").read_text())
    raw["figures"]["volumetric_max_um"].update(status=None, limit=None)
    (tmp_path / "m.json").write_text(json.dumps(raw))
    code, _, se = run_cli(["map", "--machine", str(MACHINE), "--map", str(tmp_path / "m.json"),
                           "--report", str(tmp_path / "r")])
    assert code == 0, se
    html = (tmp_path / "r" / "map.html").read_text(encoding="utf-8")
    mx = _rows(html, "map-figures")[1][2]
    assert mx[2] == "—" and "not judged" in mx[3]
    assert '<span class="badge">NOT JUDGED</span>' in html and ">PASS<" not in html


def test_the_words_follow_the_observability_statement(report):
    """Scale unobservable (no calibrated distance): said first; functions sharing a reason are
    named on one line; a link the statement names is listed."""
    from daemon.reports.map_text import unobservable_lines

    doc = report[1]
    obs = doc.observability
    lines = unobservable_lines(doc)
    assert not any(x.startswith("Isotropic scale") for x in lines)
    stmt = {"isotropic_scale": "no calibrated distance", **obs.unobservable}
    lines = unobservable_lines(doc.model_copy(update={"observability": obs.model_copy(
        update={"scale_observable": False, "unobservable": stmt})}))
    assert lines[0] == "Isotropic scale of the linear axes: no calibrated distance"
    gone = [f.name for f in doc.functions if not f.terms]
    by_y = [n for n in gone if n[2] == "Y"]
    assert f"{', '.join(by_y)} are not observable: with one stylus" in "\n".join(lines)
    links = [k for k in obs.unobservable if "_P" not in k and len(k) == 4]
    assert links and all(k in next(x for x in lines if x.startswith("Link errors"))
                         for k in links)
