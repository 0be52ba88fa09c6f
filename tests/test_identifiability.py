"""The identifiable link set is derived from the Jacobian, not hand-listed (METHOD.md §2)."""

from pathlib import Path

import pytest

from contracts.setup_files import load_artefact, load_machine, load_plan
from identification.identifiability import identifiable_links, nominal_centres

CFG = Path(__file__).resolve().parents[1] / "config"
THESIS_EIGHT = {"EB0Z", "EA0Y", "EC0Y", "EA0B", "EC0B", "EX0C", "EA0C", "EB0C"}


def _ident(machine: str, artefact: str, plan: str):
    m, _ = load_machine(CFG / "machines" / f"{machine}.yaml")
    a = load_artefact(CFG / "artefacts" / f"{artefact}.yaml")
    p = load_plan(CFG / "plans" / f"{plan}.yaml")
    c = nominal_centres(m, a, [(q.b_deg, q.c_deg) for q in p.poses])
    return identifiable_links(m, a, c)


@pytest.mark.parametrize("plan", ["thesis_ch3_7poses", "thesis_annexB_14poses",
                                  "thesis_ch4_175poses"])
def test_thesis_machine_gives_table_b2_eight(plan: str) -> None:
    r = _ident("thesis_wcbxfzyt", "thesis_4ball", plan)
    assert set(r.links) == THESIS_EIGHT
    # What is dropped is named with what absorbs it: constant offsets go to the probe setup.
    assert r.dropped["EX0B"] == "probe dx"
    assert r.dropped["EY0C"] == "probe dy"
    assert not r.scale_observable


def test_scale_observable_with_calibrated_distance() -> None:
    r = _ident("thesis_wcbxfzyt", "thesis_4ball_scaled", "thesis_annexB_14poses")
    assert r.scale_observable


def test_vertical_trunnion_set() -> None:
    r = _ident("vertical_wcayfxzt", "vertical_4ball", "vertical_18poses")
    assert set(r.links) == {"EB0A", "EC0A", "EY0C", "EA0C", "EB0C", "EC0X", "EA0Z", "EB0Z"}


def test_single_indexation_is_rejected() -> None:
    m, _ = load_machine(CFG / "machines" / "thesis_wcbxfzyt.yaml")
    a = load_artefact(CFG / "artefacts" / "thesis_4ball.yaml")
    c = nominal_centres(m, a, [(0.0, 0.0)])
    # One indexation: the probe and ball setups are the same translation, a clear error.
    with pytest.raises(ValueError, match="not identifiable"):
        identifiable_links(m, a, c)
