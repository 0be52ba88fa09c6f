"""The cycle time's lower bound without scipy: its minimum spanning tree is scipy's to the bit."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.sparse.csgraph import minimum_spanning_tree
from scipy.spatial.distance import cdist

from contracts.setup_files import load_artefact, load_machine, load_plan
from programs.cycletime import mst_length_mm
from programs.generate import generate

CFG = Path(__file__).resolve().parents[1] / "config"


def _scipy(p: np.ndarray) -> float:
    return float(minimum_spanning_tree(cdist(p, p)).sum())


def test_random_points_give_scipys_length_to_the_bit():
    rng = np.random.default_rng(1)
    for n in (2, 3, 5, 20, 41):
        for _ in range(50):
            p = rng.normal(size=(n, 3)) * 100.0
            assert mst_length_mm(p) == _scipy(p)
    assert mst_length_mm(np.zeros((1, 3))) == 0.0


@pytest.mark.parametrize(("machine", "artefact", "plan"), [
    ("thesis_wcbxfzyt", "thesis_4ball", "thesis_annexB_14poses"),
    ("linuxcnc_xyzbc", "thesis_4ball", "linuxcnc_7poses"),
])
def test_the_touch_starts_of_shipped_plans_give_scipys_length(machine, artefact, plan):
    """Each pose's touch start points, as the lower bound takes them: symmetric about the
    balls, so distances may tie and another tree of the same length be found."""
    m, mf = load_machine(CFG / f"machines/{machine}.yaml")
    g = generate(m, mf, load_artefact(CFG / f"artefacts/{artefact}.yaml"),
                 load_plan(CFG / f"plans/{plan}.yaml"), "fanuc")
    groups: dict[tuple[int, int], list] = {}
    for t in g.program.touches:
        groups.setdefault((t.id.repeat, t.id.pose), []).append(t.start)
    for pts in groups.values():
        p = np.array(pts)
        assert mst_length_mm(p) == pytest.approx(_scipy(p), rel=1e-14)
