"""The verdict rules: absolute limits, guard band on uncertainty, drift vs a baseline run."""

from __future__ import annotations

import math
from dataclasses import replace

from daemon.analysis.judge import judge, volumetric_max_um
from daemon.analysis.result import Analysis, Estimation, Health, LinkError, VolumetricPoint
from daemon.machines.tolerances import Limit, Tolerances


def analysis(eb0c=10.0, std=1.0, ex0c=-20.0, vol=(30.0, 40.0, 0.0), rms=0.8) -> Analysis:
    return Analysis(
        links={"EB0C": LinkError(eb0c, std, "urad"), "EX0C": LinkError(ex0c, 0.2, "um")},
        volumetric=(VolumetricPoint(0, ball="B1", error_um=(1.0, 2.0, 2.0)),
                    VolumetricPoint(1, ball="B2", error_um=tuple(vol))),
        residual_rms_um=rms)


TOL = Tolerances(links={"EB0C": Limit(warn=20, fail=40, drift_warn=5, drift_fail=10)},
                 default_translation_um=Limit(warn=50, fail=100),
                 volumetric_max_um=Limit(warn=60, fail=80), residual_rms_um=3.0)


def test_volumetric_max_is_the_largest_vector_norm():
    assert math.isclose(volumetric_max_um(analysis()), 50.0)
    assert volumetric_max_um(Analysis()) is None


def test_pass_within_every_limit():
    j = judge(analysis(), TOL, analysis())
    assert j.status == "PASS" and j.reasons == ()
    assert {c.quantity for c in j.checks} == {"EB0C", "EX0C",
                                              "max volumetric distortion (probed poses)",
                                              "residual RMS", "EB0C drift"}
    assert "max volumetric distortion (probed poses) 50.0 µm" in j.summary


def test_warn_and_fail_on_absolute_limits_with_sign():
    j = judge(analysis(eb0c=-25.0), TOL)
    assert j.status == "WARN" and j.reasons[0].startswith("EB0C = -25.00 ± 1.00 µrad")
    j = judge(analysis(eb0c=-25.0, ex0c=120.0), TOL)
    assert j.status == "FAIL"
    assert any(r.startswith("EX0C = +120.00") and "fail 100" in r for r in j.reasons)


def test_uncertainty_guard_band_warns_when_conformance_not_proven():
    # 15 µrad is inside warn 20, but 15 + 2 × 13 > fail 40: the data cannot prove conformance
    j = judge(analysis(eb0c=15.0, std=13.0), TOL)
    assert j.status == "WARN" and "conformance not proven" in j.reasons[0]
    assert judge(analysis(eb0c=15.0, std=2.0), TOL).status == "PASS"


def test_guard_band_widens_when_the_uncertainty_rests_on_few_residuals():
    # 15 + 2 × 12.3 = 39.6 < 40: PASS with σ known; with σ from ν = 5 residual dof the stated
    # u is already the t's standard deviation (s·√(5/3), GUM-S1), and the 95.45 % factor is
    # the t(5) quantile 2.65 over √(5/3) = 2.05: 15 + 2.05 × 12.3 > 40 (the old rule applied
    # 2.65 to that u: ×1.29 too wide)
    a = analysis(eb0c=15.0, std=12.3)
    assert judge(a, TOL).status == "PASS"
    j = judge(replace(a, estimation=Estimation(sigma_dof=5.0)), TOL)
    assert j.status == "WARN" and "|value| + 2.05u" in j.reasons[0], j.reasons
    assert judge(replace(a, estimation=Estimation(sigma_dof=500.0)), TOL).status == "PASS"
    # 15 + 2.05 × 11.5 = 38.6: the old rule (15 + 2.65 × 11.5 = 45.5) warned here
    assert judge(replace(analysis(eb0c=15.0, std=11.5), estimation=Estimation(sigma_dof=5.0)),
                 TOL).status == "PASS"


def test_drift_against_the_baseline_run():
    ref = replace(analysis(eb0c=10.0), run_id="B1")
    assert judge(analysis(eb0c=13.0), TOL, ref).status == "PASS"
    j = judge(analysis(eb0c=17.0), TOL, ref)
    assert j.status == "WARN" and "EB0C drift: +7.00" in j.reasons[0]
    assert "since baseline run B1 (was +10.00)" in j.reasons[0]
    assert [c.reference_run for c in j.checks if c.quantity == "EB0C drift"] == ["B1"]
    assert judge(analysis(eb0c=-1.0), TOL, ref).status == "FAIL"


def test_no_baseline_is_said_never_silently_dropped():
    """Without a baseline the drift is not checked, and the verdict says so (it
    used to drop the drift checks silently when no PASS run existed)."""
    j = judge(analysis(eb0c=17.0), TOL, None)
    assert j.status == "PASS" and not any("drift" in c.quantity for c in j.checks)
    assert [r for r in j.reasons if r.startswith("drift not checked: no baseline")]
    no_drift = replace(TOL, links={"EB0C": Limit(warn=20, fail=40)})
    assert judge(analysis(), no_drift, None).reasons == ()  # no drift limits: nothing to say


def test_volumetric_and_health_limits():
    assert judge(analysis(vol=(0, 70.0, 0)), TOL).status == "WARN"
    j = judge(analysis(vol=(0, 0, -90.0)), TOL)
    assert j.status == "FAIL" and "max volumetric distortion (probed poses) = +90.00 µm" in \
        j.reasons[0]
    j = judge(analysis(rms=4.0), TOL)
    assert j.status == "ERROR" and "residual RMS" in j.reasons[0]
    assert "measurement not trusted" in j.reasons[0]
    j = judge(Analysis(), Tolerances(volumetric_max_um=Limit(fail=10)))
    assert j.status == "FAIL"  # a limit on something missing never passes silently


def test_tolerance_on_unidentified_link_is_reported():
    tol = Tolerances(links={"EA0Y": Limit(fail=10)})
    j = judge(analysis(), tol)
    assert j.status == "PASS"
    assert j.reasons == ("EA0Y: tolerance given but not identified in this run",)


def test_one_bad_sphere_makes_the_measurement_untrusted():
    health = [Health(p, ball=b, radius_dev_um=1.0 + 0.1 * p, form_rms_um=0.3)
              for p in range(5) for b in ("B1", "B2")]
    a = replace(analysis(), health=tuple(health))
    assert judge(a, TOL).status == "PASS"  # a common radius offset (pre-travel) is fine
    health[7] = replace(health[7], radius_dev_um=9.0)  # pose 3, ball B2: a chip or early trigger
    j = judge(replace(a, health=tuple(health)), TOL)
    assert j.status == "ERROR" and j.checks[0].status == "ERROR"
    assert j.reasons[0].startswith("sphere radius, ball B2 pose 3 = +7.80 µm")
