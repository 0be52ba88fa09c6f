"""End to end through the product: the daemon's program for the thesis annex-B 14-pose plan,
executed by `rumba sim --run` on the thesis machine (Table B.2 links, setup errors, §3.4 noise),
analysed by `rumba analyze`'s own function; the link errors come back within 3 standard
uncertainties."""

from __future__ import annotations

import numpy as np

from contracts.setup_files import load_artefact, load_machine, load_plan
from daemon.cli.commands.analyze import run_analysis
from daemon.cli.main import main
from programs.dialects import get_dialect
from programs.toolpath import build_program
from simulators.errors_schema import load_errors

MACHINE = "config/machines/thesis_wcbxfzyt.yaml"
ARTEFACT = "config/artefacts/thesis_4ball.yaml"
ERRORS = "config/errors/thesis_tableB2.yaml"


def test_table_b2_recovered_within_3_sigma(tmp_path, capsys):
    m, mf = load_machine(MACHINE)
    a = load_artefact(ARTEFACT)
    prog = build_program(m, mf, a, load_plan("config/plans/thesis_annexB_14poses.yaml"))
    nc = tmp_path / "annexb.nc"
    nc.write_text(get_dialect("fanuc").render(prog))
    log = tmp_path / "annexb.csv"
    assert main(["sim", "--machine", MACHINE, "--artefact", ARTEFACT, "--errors", ERRORS,
                 "--run", str(nc), "--dialect", "fanuc", "--log", str(log), "--seed", "3"]) == 0
    assert "280 touches logged" in capsys.readouterr().out
    # Covariance from the known probing repeatability (thesis §3.4), as `--repeatability-um`:
    # over 20 seeds the worst of the 8 |error|/std exceeded 3 once (expected for 8 normals).
    res = run_analysis(log, MACHINE, ARTEFACT, repeatability_um=[0.66, 0.98, 0.44]).to_json()
    truth = load_errors(ERRORS)
    assert set(res["links"]) == set(truth.links)
    for name, est in res["links"].items():
        assert abs(est["value"] - truth.links[name]) < 3 * est["std"], (name, est)
        assert est["std"] < 4.0  # µrad / µm: the thesis-level precision, not a vague pass
    # The residuals agree with that repeatability (reduced chi-square near 1).
    assert 0.4 < res["residual_rms_um"] < 1.2
    for ball, want in truth.setup.balls_um.items():
        got = np.array(res["setup"]["balls"][ball]["value"])
        assert np.max(np.abs(got - want)) < 5.0, (ball, got, want)  # µm, of ~300 µm errors
