"""The typed analysis result: its JSON is the file format, so JSON → Analysis → JSON is exact."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest

from daemon.analysis.result import Analysis, LinkError, Stability
from daemon.cli.commands.analyze import run_analysis

CFG = Path("config")
LOG = CFG / "examples/thesis_annexB_14poses.csv"
MACHINE = CFG / "machines/thesis_wcbxfzyt.yaml"


def _text(a: Analysis) -> str:
    return json.dumps(a.to_json(), indent=1, ensure_ascii=False)


@pytest.mark.parametrize(("artefact", "validate"), [
    ("thesis_4ball.yaml", [3, 4, 5, 7, 9, 10, 11]), ("thesis_4ball_scaled.yaml", [])])
def test_json_round_trip_is_byte_identical(artefact: str, validate: list[int]) -> None:
    a = run_analysis(LOG, MACHINE, CFG / "artefacts" / artefact, validate_poses=validate)
    text = _text(a)
    back = Analysis.from_json(json.loads(text))
    assert back == a and _text(back) == text
    doc = a.to_json()
    assert list(doc)[:4] == ["log", "machine", "topology", "artefact"]
    assert ("validation" in doc) == bool(validate)
    assert ("scale_um_per_m" in doc) == ("scaled" in artefact)
    assert "run_id" not in doc and "reference_run" not in doc and "stability" not in doc


def test_a_journaled_run_states_its_reference_even_when_none() -> None:
    a = Analysis(machine="mill1", links={"EX0C": LinkError(-1.5, 0.2, "um")})
    assert "reference_run" not in a.to_json()
    run = replace(a, run_id="R1", plan="p", touches=3)
    doc = run.to_json()
    assert list(doc) == ["run_id", "machine", "plan", "topology", "artefact", "links",
                         "residual_rms_um", "condition_number", "unobservable",
                         "unobservable_absorbed_by", "volumetric", "cluster", "distances",
                         "health", "warnings", "conventions", "touches", "reference_run"]
    assert doc["reference_run"] is None
    assert Analysis.from_json(replace(run, reference_run="R0").to_json()).reference_run == "R0"


def test_nested_parts_and_nulls_come_back_typed() -> None:
    doc = {"machine": "m", "links": {"EB0C": {"value": 1.0, "std": None, "unit": "urad",
                                              "thesis_name": "βC"}},
           "stability": {"convention": "c", "max_shift_um": 2.5,
                         "worst": {"pose": 0, "ball": "B1"}, "span_min": None,
                         "revisits": [{"pose": 0, "ball": "B1", "repeats": [0, 1],
                                       "dt_min": 4.0, "shift_um": [0.0, None, 2.5],
                                       "norm_um": 2.5}]}}
    a = Analysis.from_json(doc)
    assert isinstance(a.stability, Stability) and a.stability.worst.ball == "B1"
    assert a.stability.revisits[0].shift_um == (0.0, None, 2.5)
    assert a.links["EB0C"].std is None
    assert a.to_json()["stability"] == doc["stability"]


def test_a_malformed_part_is_refused_with_its_name() -> None:
    with pytest.raises(ValueError, match="Stability must be an object"):
        Analysis.from_json({"stability": [1, 2]})
