"""The stated-repeatability decision (identification/estimate_scatter.py ``with_stated``) made
once and carried as data (found in review): ``Estimate.stated_used`` is what every screen
shows, on the plain and the drift-aware path, and the drift refit replaces exactly the plain
fit's scatter warnings (``Estimate.scatter_warnings``), never a warning that merely reads
alike."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from daemon.analysis.identify import analyse_centres
from daemon.analysis.touch_centres import CentreData
from daemon.reports.index_scatter import index_scatter_lines
from identification.drift import fit_drift
from identification.estimate import estimate
from identification.model import Centres
from identification.visit_scatter import LR_ALPHA
from tests.test_estimate_stated import _centres, shift_visits


@pytest.fixture(scope="module")
def sv():
    return shift_visits()


def _shown(sv, c: Centres, stated: dict[str, float]):
    """(the analysis' index scatter lines, its entries by axis, the estimate it rests on):
    the daemon's path (``analyse_centres``: drift-aware) on the centres ``c``."""
    keep: dict = {}
    an = analyse_centres(sv.machine, sv.artefact,
                         CentreData(c, np.zeros(len(c), np.int64), [], []), keep=keep,
                         rotary_repeatability_urad=stated)
    return index_scatter_lines(an), {x.axis: x for x in an.estimation.index_scatter}, \
        keep["estimate"], an


def _agrees(est, lines: list[str], ix: dict, warnings: list[str]) -> None:
    """Per rotary axis the report's "used" is the estimate's decision, its p the test's side
    of it, and the report's warnings of that axis are the estimate's scatter warnings."""
    for ax, x in ix.items():
        used = f"index {ax}" in est.stated_used
        assert x.used == ("stated" if used else "estimated")
        assert any(ln.startswith(f"{ax} indexing repeatability") and
                   ln.split(", used: ")[1].startswith(x.used) for ln in lines), lines
        assert (x.p_stated >= LR_ALPHA) == used, (ax, x.p_stated, est.stated_used)
    assert [ln[9:] for ln in lines if ln.startswith("Warning: ")] == \
        list(est.scatter_warnings)
    assert all(w in warnings for w in est.scatter_warnings)


def test_one_axis_stated_used_the_other_overridden_as_the_report_shows(sv):
    """10 µrad true scatter, the file states B 10 and C 1: the plain estimate holds B at its
    stated value and overrides C, one warning naming C; the analysis shows exactly that."""
    m, a = sv.machine, sv.artefact
    c = _centres(sv, 2, 10.0)
    stated = {"B": 10.0, "C": 1.0}
    est = estimate(m, a, c, rotary_repeatability_urad=stated)
    assert est.stated_used == ("index B",)
    assert [w[:2] for w in est.scatter_warnings] == ["C "]
    assert "machine file states 1 " in est.scatter_warnings[0]
    assert est.scatter_warnings[0] in est.warnings  # every consumer of warnings still sees it
    assert estimate(m, a, c).stated_used == () == estimate(m, a, c).scatter_warnings
    lines, ix, shown, an = _shown(sv, c, stated)
    assert shown.stated_used == ("index B",)
    assert (ix["B"].used, ix["C"].used) == ("stated", "estimated")
    _agrees(shown, lines, ix, list(an.warnings))


def test_the_drift_aware_path_shows_the_refits_decision_not_the_plain_fits(sv):
    """A 20 µm warm-up left in the plain fit's residuals reads as index scatter on some runs:
    here (4 µrad true, 2 stated) the plain fit keeps both stated values and the drift refit,
    on the residuals the drift leaves, overrides C. The estimate carries the refit's decision
    and warning, and the analysis shows those."""
    m, a = sv.machine, sv.artefact
    c = _centres(sv, 5, 4.0, warmup_um=20.0)
    stated = {"B": 2.0, "C": 2.0}
    base = estimate(m, a, c, rotary_repeatability_urad=stated)
    assert base.stated_used == ("index B", "index C") and base.scatter_warnings == ()
    out = fit_drift(m, a, c, base, stated_urad=stated)
    assert out.status == "selected", out.message
    assert out.estimate.stated_used == ("index B",)
    assert [w[:2] for w in out.estimate.scatter_warnings] == ["C "]
    lines, ix, shown, an = _shown(sv, c, stated)
    assert an.thermal is not None and an.thermal.status == "selected"
    assert shown.stated_used == ("index B",)
    assert (ix["B"].used, ix["C"].used) == ("stated", "estimated")
    _agrees(shown, lines, ix, list(an.warnings))


def test_the_refit_replaces_the_plain_fits_scatter_warnings_and_keeps_the_rest(sv):
    """Here (4 µrad true, 3 stated, 20 µm warm-up) the plain fit overrides B and the refit
    keeps both stated: the plain fit's scatter warning goes; a warning of the plain fit that
    happens to read "machine file states" but is no scatter verdict stays."""
    m, a = sv.machine, sv.artefact
    c = _centres(sv, 4, 4.0, warmup_um=20.0)
    stated = {"B": 3.0, "C": 3.0}
    base = estimate(m, a, c, rotary_repeatability_urad=stated)
    assert base.stated_used == ("index C",)
    assert [w[:2] for w in base.scatter_warnings] == ["B "]
    other = "probe: the machine file states no stylus length; the plan's 100 mm is used"
    base = replace(base, warnings=[*base.warnings, other])
    out = fit_drift(m, a, c, base, stated_urad=stated)
    assert out.status == "selected", out.message
    e = out.estimate
    assert e.stated_used == ("index B", "index C") and e.scatter_warnings == ()
    assert other in e.warnings
    assert not set(base.scatter_warnings) & set(e.warnings), e.warnings
    # the plain fit's other warnings pass through as before, in order
    rest = [w for w in base.warnings if w not in base.scatter_warnings]
    assert e.warnings[:len(rest)] == rest


def test_the_stored_estimate_keeps_the_decision_and_an_old_file_still_loads(sv):
    """The compensation's stored estimate (daemon/compensation/identified.py) carries the
    decision and the scatter warnings; a file written before them loads with none."""
    import json

    from daemon.compensation.identified import from_json, to_json

    est = estimate(sv.machine, sv.artefact, _centres(sv, 2, 10.0),
                   rotary_repeatability_urad={"B": 10.0, "C": 1.0})
    back = from_json(to_json(est))
    assert back.stated_used == ("index B",) and back.scatter_warnings == est.scatter_warnings
    assert len(back.scatter_warnings) == 1
    old = json.loads(to_json(est))
    del old["stated_used"], old["scatter_warnings"]
    legacy = from_json(json.dumps(old))
    assert legacy.stated_used == () == legacy.scatter_warnings
    assert legacy.warnings == est.warnings and set(legacy.visit_scatter) == set(est.visit_scatter)
