"""A knocked ball named (simlog and the G-code simulator), a creep is no step, the
example log's verdict."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from benchmarks.rigs.gap_helpers import (
    ARTEFACT,
    CONFIG,
    EXAMPLE,
    MACHINE,
    STYLUS_R,
    annex_b_setup,
    gap_truth,
    scatter_components,
)
from contracts.setup_files import load_artefact, load_machine, plan_from_dict
from contracts.yaml_files import ConfigError
from daemon.cli.main import main
from identification.effects import make_effect
from identification.gap import diagnose
from identification.gap.selfcheck import run_case
from identification.gap.simlog import simulate


@pytest.fixture(scope="module")
def setup():
    return annex_b_setup()


def test_knocked_ball_is_named_with_ball_moment_and_size(setup):
    machine, artefact, poses = setup
    case = run_case(machine, artefact, poses, STYLUS_R, "ball_step", None, seed=1017,
                    plan="14")
    assert case.ok and case.verdict == "ball_moved", case


def test_a_creeping_ball_is_no_step(setup):
    # A constant-velocity creep leans on the later visits too; the library's creep must win.
    machine, artefact, poses = setup
    eff = make_effect("artefact_instability", "B2", machine, ball_index=1)
    truth = gap_truth(artefact, seed=5, effects=[(eff, np.array([6.0, -8.0, 3.0]))])  # µm/h
    data = simulate(machine, artefact, poses, truth, STYLUS_R, 0.5, seed=105)
    rep = diagnose(machine, artefact, data, STYLUS_R)
    assert rep["ball_step"] is None
    assert (rep["verdict"]["effect"], rep["verdict"]["axis"]) == ("artefact_instability", "B2")


def test_simulator_indexes_with_scatter_and_knocks_a_ball(tmp_path):
    # The G-code simulator through its errors file: index scatter per indexation and a step.
    from benchmarks.rigs.gap_helpers import gap_json, scatter_components
    from programs.dialects import get_dialect
    from programs.toolpath import build_program
    from simulators.errors_schema import errors_from_dict
    from simulators.offline import run_sync
    from simulators.truth import TruthModel

    m, mf = load_machine(MACHINE)
    a = load_artefact(ARTEFACT)
    plan = plan_from_dict(yaml.safe_load((CONFIG / "plans/thesis_annexB_14poses.yaml")
                                         .read_text()))
    errors = yaml.safe_load((CONFIG / "errors/thesis_tableB2.yaml").read_text())
    errors |= {"indexing": {"repeatability_urad": {"B": 10, "C": 10}},
               "ball_steps": [{"ball": "B2", "t_s": 100, "vector_um": [6, -5, 3]}]}
    truth = TruthModel.build(m, mf, a, errors_from_dict(errors))
    res = run_sync(truth, get_dialect("linuxcnc").render(build_program(m, mf, a, plan)),
                   "linuxcnc", seed=2)
    rep = gap_json(tmp_path / "log.csv", res.rows, tmp_path / "gap.json")
    step = rep["ball_step"]
    assert rep["verdict"]["effect"] == "ball_moved" and step["ball"] == "B2"
    assert abs(step["size_um"] - np.linalg.norm([6, -5, 3])) < 1.0
    assert step["t_after_s"] < 100 < step["t_before_s"]
    assert rep["verdict"]["with_step_modelled"]["effect"] == "none"
    assert all(scatter_components(rep)[f"index {x}"]["detected"] for x in "BC")
    for bad, key in (({"indexing": {"repeatability_urad": {"A": 3}}}, "repeatability_urad.A"),
                     ({"ball_steps": [{"ball": "B9", "t_s": 1, "vector_um": [1, 0, 0]}]},
                      "ball_steps[0].ball")):
        with pytest.raises(ConfigError, match=key.replace("[", r"\[").replace("]", r"\]")):
            TruthModel.build(m, mf, a, errors_from_dict(errors | bad), where="e.yaml")


def test_example_log_verdict_is_true_of_how_it_was_made(tmp_path, capsys):
    # tests/regen_example_log.py: Table B.2 links, the thesis' centre repeatability as an
    # independent scatter per ball visit (0.62 / 0.96 / 0.29 µm on top of 0.3 µm touch
    # noise), nothing else. Unscattered: "unexplained — 12.51× the floor, p = 1.4e-25".
    out = tmp_path / "gap.json"
    assert main(["gap", "--log", str(EXAMPLE), "--machine", str(MACHINE), "--artefact",
                 str(ARTEFACT), "--json", str(out)]) == 0
    rep = json.loads(out.read_text())
    assert rep["verdict"]["effect"] == "none"
    comp = scatter_components(rep)
    assert comp["centre x"]["detected"] and comp["centre y"]["detected"]
    assert 0.4 < comp["centre x"]["sigma"] < 0.85 and 0.7 < comp["centre y"]["sigma"] < 1.3
    assert not comp["index B"]["detected"] and not comp["index C"]["detected"]
    assert "centre scatter y per ball visit ≈" in capsys.readouterr().out


def test_selfcheck_gains_the_scatter_conditions(setup):
    # rumba gap --selfcheck: every library effect and the null run again under indexing
    # scatter, and a knocked ball; an effect under scatter is scaled to the floor *with* it.
    from identification.effects import FAMILIES
    from identification.gap import selfcheck
    from identification.gap.selfcheck_scatter import SCATTER_URAD, index_rms_um, split_scatter

    machine, artefact, poses = setup
    added = set(selfcheck.SCENARIOS) - set(selfcheck.BASE_SCENARIOS)
    structure = {"cyclic_error", "local_bump"}  # outside the library: test_gap_structure.py
    assert added == {f"{f}+scatter" for f in (*FAMILIES, *selfcheck.VARIANTS, "null")} | {
        "ball_step", "pole_chip+scatter"} | structure | {f"{s}+scatter" for s in structure}
    assert selfcheck.expected_family("pole_chip+scatter") is None  # a control: named visit
    assert split_scatter("gravity_sag+scatter") == ("gravity_sag", True)
    assert selfcheck.expected_family("radial2_fixed+scatter") == "rotary_error_motion"
    assert selfcheck.axes_of("rotary_positioning+scatter", machine, artefact) == ["B", "C"]
    one = index_rms_um(machine, artefact, poses, 1.0)
    assert index_rms_um(machine, artefact, poses, SCATTER_URAD) == pytest.approx(
        SCATTER_URAD * one)
    assert 0.02 < one < 0.5  # µm per µrad: balls 100-300 mm from the rotary axes
