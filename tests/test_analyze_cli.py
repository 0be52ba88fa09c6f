"""`rumba analyze` end to end: JSON contract, summary, one-line errors (exit 2), demo log."""

import json
from pathlib import Path

import numpy as np
import pytest

from contracts.probing_log import HEADER, write_log
from contracts.setup_files import load_artefact, load_machine, load_plan
from daemon.cli.commands.analyze import run_analysis
from daemon.cli.main import main
from simulators.exact_log import THESIS_LINKS_UM_URAD, Truth, make_rows, to_internal

ROOT = Path(__file__).resolve().parents[1]
CFG = ROOT / "config"
MACHINE = str(CFG / "machines/thesis_wcbxfzyt.yaml")
ARTEFACT = str(CFG / "artefacts/thesis_4ball.yaml")
PLAN = load_plan(CFG / "plans/thesis_annexB_14poses.yaml")
VALIDATE = ",".join(str(i) for i in PLAN.indices("validate"))


@pytest.fixture(scope="module")
def log(tmp_path_factory) -> Path:
    m, _ = load_machine(MACHINE)
    a = load_artefact(ARTEFACT)
    truth = Truth(to_internal(THESIS_LINKS_UM_URAD), np.full((4, 3), 0.2),
                  np.array([0.1, -0.1, 0.2]))
    rows = make_rows(m, a, [(p.b_deg, p.c_deg) for p in PLAN.poses], truth,
                     touch_noise_um=0.5, seed=4)
    p = tmp_path_factory.mktemp("log") / "run.csv"
    write_log(p, rows)
    return p


def _args(log: Path, *extra: str) -> list[str]:
    return ["analyze", "--log", str(log), "--machine", MACHINE, "--artefact", ARTEFACT, *extra]


def test_json_contract_and_summary(log: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "r.json"
    assert main(_args(log, "--validate-poses", VALIDATE, "--json", str(out))) == 0
    text = capsys.readouterr().out
    for want in ("Link errors", "EX0C", "δxC offset CB", "µrad", "Setup errors (µm)",
                 "residual RMS", "condition number", "isotropic_scale", "Validation"):
        assert want in text
    r = json.loads(out.read_text())
    assert set(r["links"]) == {"EB0Z", "EA0Y", "EC0Y", "EA0B", "EC0B", "EX0C", "EA0C", "EB0C"}
    assert r["links"]["EX0C"]["unit"] == "um" and r["links"]["EB0Z"]["unit"] == "urad"
    for k, v in r["links"].items():
        assert abs(v["value"] - THESIS_LINKS_UM_URAD[k]) < 4 * v["std"]
    assert r["setup"]["probe"]["value"] == pytest.approx([100, -100, 200], abs=3)
    assert r["setup"]["balls"]["B3"]["value"] == pytest.approx([200] * 3, abs=3)
    assert len(r["setup"]["balls"]["B1"]["std"]) == 3
    assert 0.1 < r["residual_rms_um"] < 1.0 and r["condition_number"] > 1
    assert "isotropic_scale" in r["unobservable"] and "scale_um_per_m" not in r
    assert len(r["volumetric"]) == 56
    v0 = r["volumetric"][0]
    assert set(v0) >= {"pose", "b_deg", "c_deg", "ball", "error_um", "error_after_links_um"}
    assert len(r["cluster"]) == 14 and len(r["cluster"][0]["local_um"]["B1"]) == 3
    assert len(r["cluster"][0]["linear_um"]) == 3 and len(r["cluster"][0]["angular_urad"]) == 3
    assert len(r["distances"]) == 6 * 14 and "deviation_um" in r["distances"][0]
    val = r["validation"]
    assert val["explained_fraction"] > 0.9 and val["max_after_um"] < val["max_before_um"]
    assert len(r["health"]) == 56 and r["estimation"]["centres"] == 28


def test_links_none_and_list(log: Path, tmp_path: Path) -> None:
    r = run_analysis(log, MACHINE, ARTEFACT, links="none")
    assert r.links == {} and r.residual_rms_um > 5.0  # links left in the residual
    r = run_analysis(log, MACHINE, ARTEFACT, links="ex0c,EB0Z", fixed_radius=True,
                     repeatability_um=[0.66, 0.98, 0.44])
    assert r.estimation is not None
    assert set(r.links) == {"EX0C", "EB0Z"} and r.estimation.fixed_radius
    assert r.estimation.sigma_um == (0.66, 0.98, 0.44)
    assert r.estimation.sigma_from == "given"


def test_scale_reported_with_calibrated_artefact(log: Path) -> None:
    r = run_analysis(log, MACHINE, CFG / "artefacts/thesis_4ball_scaled.yaml")
    assert "isotropic_scale" not in r.unobservable
    assert set(r.to_json()["scale_um_per_m"]) == {"value", "std"}


@pytest.mark.parametrize(("extra", "match"), [
    (["--links", "EQ0Z"], "--links: unknown link error"),
    (["--validate-poses", "3,99"], "poses [99] are not in"),
    (["--validate-poses", "a,b"], "expected a comma list of pose numbers"),
    (["--repeatability-um", "0.5,-1,2"], "--repeatability-um: expected one or three positive"),
])
def test_option_errors_are_one_line_exit_2(log: Path, capsys, extra, match) -> None:
    assert main(_args(log, *extra)) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and match in err and err.count("\n") == 1


def test_bad_log_and_rank_deficient_log(log: Path, tmp_path: Path, capsys) -> None:
    bad = tmp_path / "bad.csv"
    lines = log.read_text().splitlines()
    bad.write_text("\n".join([*lines[:10], lines[10].replace(",B2,", ",B7,"), *lines[11:]]))
    assert main(_args(bad)) == 2
    err = capsys.readouterr().err
    assert f"{bad}: line 11: column ball: unknown ball id 'B7'" in err
    one_pose = tmp_path / "one.csv"
    one_pose.write_text("\n".join(lines[:22]))  # header + pose 0 only (4 balls × 5 touches)
    assert main(_args(one_pose)) == 2
    assert "rank-deficient pose set" in capsys.readouterr().err
    assert main(_args(tmp_path / "missing.csv")) == 2
    assert "cannot read" in capsys.readouterr().err
    assert main(["analyze", "--log", str(log), "--machine", str(tmp_path / "m.yaml"),
                 "--artefact", ARTEFACT]) == 2


def _cells(path: Path) -> list[list[str]]:
    """The log's rows split into cells (x_mm, y_mm, z_mm are columns 12-14)."""
    lines = path.read_text(encoding="utf-8").splitlines()
    assert lines[1].split(",")[12:15] == ["x_mm", "y_mm", "z_mm"]
    return [ln.split(",") for ln in lines[2:]]


def test_shipped_example_log_is_reproducible_and_analysed(tmp_path: Path) -> None:
    from tests.regen_example_log import OUT
    from tests.regen_example_log import main as regen

    regen(tmp_path / "again.csv")
    # the same rows; the latched positions to 1e-9 mm (the generator's chain runs through BLAS,
    # whose kernels differ in the last bits: 3e-14 mm seen on Prescott against AVX-512), every
    # other column exactly
    head = [p.read_text(encoding="utf-8").splitlines()[:2] for p in (tmp_path / "again.csv", OUT)]
    assert head[0] == head[1]
    again, shipped = _cells(tmp_path / "again.csv"), _cells(OUT)
    assert [r[:12] + r[15:] for r in again] == [r[:12] + r[15:] for r in shipped]
    np.testing.assert_allclose([[float(x) for x in r[12:15]] for r in again],
                               [[float(x) for x in r[12:15]] for r in shipped], rtol=0, atol=1e-9)
    r = run_analysis(OUT, MACHINE, ARTEFACT, validate_poses=PLAN.indices("validate"))
    assert r.links["EX0C"].value == pytest.approx(-106, abs=2)
    assert r.validation is not None and r.validation.explained_fraction > 0.9


def test_repeats_give_one_centre_and_cluster_per_repeat(tmp_path: Path) -> None:
    m, _ = load_machine(MACHINE)
    a = load_artefact(ARTEFACT)
    poses = [(p.b_deg, p.c_deg) for p in load_plan(CFG / "plans/thesis_ch3_7poses.yaml").poses]
    rows = make_rows(m, a, poses, Truth(to_internal({"EX0C": -50.0})), touch_noise_um=0.3,
                     repeats=2)
    write_log(tmp_path / "rep.csv", rows)
    r = run_analysis(tmp_path / "rep.csv", MACHINE, ARTEFACT)
    assert r.estimation is not None and r.estimation.centres == 56 and len(r.health) == 56
    assert sorted((x.pose, x.repeat) for x in r.cluster) == [
        (p, k) for p in range(7) for k in (0, 1)]
    assert r.links["EX0C"].value == pytest.approx(-50.0, abs=1.0)


def _edit(log: Path, out: Path, fn) -> Path:
    """Rewrite the data rows of ``log`` with ``fn(index, cells)`` (index from 0) into ``out``."""
    lines = log.read_text().splitlines()
    rows = [line.split(",") for line in lines[2:]]
    for i, cells in enumerate(rows):
        fn(i, cells)
    out.write_text("\n".join([*lines[:2], *(",".join(c) for c in rows)]) + "\n")
    return out


X, Y, Z = (HEADER.index(c) for c in ("x_mm", "y_mm", "z_mm"))


@pytest.mark.parametrize(("value", "match"), [
    ("1e15", "line 9: column y_mm: 1e15 outside [-100000, 100000]"),
    ("1e308", "line 9: column y_mm: 1e308 outside [-100000, 100000]"),
    ("1_0.5", "line 9: column y_mm: expected a finite number, got '1_0.5' (ASCII decimal as "
              "JSON writes it: -12.5, 0.25, 1e-05; no '+', '.5', '5.' or leading zero)"),
])
def test_absurd_coordinates_are_one_line_naming_the_cell(log, tmp_path, capsys, value,
                                                          match) -> None:
    def fn(i, cells):
        if i == 6:
            cells[Y] = value
    bad = _edit(log, tmp_path / "big.csv", fn)
    assert main(_args(bad)) == 2
    err = capsys.readouterr().err
    assert err == f"error: {bad}: {match}\n"


@pytest.mark.parametrize("shape", ["identical", "collinear", "coplanar"])
def test_degenerate_touches_are_one_line_naming_ball_and_pose(log, tmp_path, capsys,
                                                               shape) -> None:
    group = range((3 * 4 + 1) * 5, (3 * 4 + 2) * 5)  # pose 3, ball B2

    def fn(i, cells):
        if i in group:
            k = i - group.start
            xyz = {"identical": (10.0, 20.0, 30.0), "collinear": (k, 2.0 * k, 3.0 * k),
                   "coplanar": (float(cells[X]), float(cells[Y]), 0.0)}[shape]
            cells[X], cells[Y], cells[Z] = (repr(float(v)) for v in xyz)
    bad = _edit(log, tmp_path / "flat.csv", fn)
    assert main(_args(bad)) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {bad}: ball B2 pose 3 repeat 0: sphere fit failed: "
                          "degenerate points") and err.count("\n") == 1


def test_non_finite_centres_are_an_analysis_error_naming_ball_and_pose(log) -> None:
    from contracts.probing_log import read_log
    from contracts.yaml_files import ConfigError
    from daemon.analysis.identify import AnalysisError, analyse_centres
    from daemon.analysis.touch_centres import rows_to_centres

    m, _ = load_machine(MACHINE)
    a = load_artefact(ARTEFACT)
    data = rows_to_centres(read_log(log, a), a, 3.0)
    data.centres.xyz_mm[5] = [1e308, np.inf, 0.0]
    with pytest.raises(AnalysisError, match=r"x.csv: centre of ball B2 pose 1 is not a finite"):
        analyse_centres(m, a, data, source="x.csv")
    data.centres.xyz_mm[5] = [1e150, -1e150, 1e150]  # finite, but the estimate cannot cope
    with pytest.raises(AnalysisError, match=r"x.csv: estimate \(setup \+ links\)"):
        analyse_centres(m, a, data, source="x.csv")
    assert issubclass(AnalysisError, ConfigError)  # the CLI prints it as one line


def test_seq_gaps_and_duplicates(log, tmp_path, capsys) -> None:
    def drop(i, cells):
        if i in (40, 41):
            cells[:] = []
    gap = _edit(log, tmp_path / "gap.csv", drop)
    gap.write_text("\n".join(x for x in gap.read_text().splitlines() if x) + "\n")
    r = run_analysis(gap, MACHINE, ARTEFACT)
    assert any("seq 41–42 missing" in w for w in r.warnings)
    assert any("ball B1 pose 2 repeat 0: only touches [3, 4, 5]" in w for w in r.warnings)

    def dup(i, cells):
        if i == 30:
            cells[1] = "2"
    assert main(_args(_edit(log, tmp_path / "dup.csv", dup))) == 2
    assert "line 33: seq 2 of run synth duplicates line 4" in capsys.readouterr().err
