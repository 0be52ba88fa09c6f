"""The demos' shop limits: derived from a stated basis, each limit with its
source, as a shop writes them into daemon.yaml (README "Choosing limits"); one copy for the
demos (make demo, make demo-hmi, make demo-fleet)."""

from __future__ import annotations

from typing import Any

PART_TOLERANCE_MM = 0.10  # the parts' position tolerance (±0.05 mm) on tilted features
MACHINE_SHARE = 1 / 3  # the machine's share; fixture, tool, thermal and gauge take the rest
LEVER_MM = 250.0  # rotary axes to the work's far corner: a rotation's lever on the tool tip

BASIS = (
    "Shop limits, demo machine (5-axis HMC, work within 250 mm of the rotary axes): parts "
    "with a 0.10 mm position tolerance on tilted features. The machine may take 1/3 of it "
    "(fixture, tool, thermal growth and gauging take the rest): 33 µm. Link errors and the "
    "volumetric distortion over the artefact's balls fail at 25-30 µm and warn at 2/3 of "
    "that, to plan a compensation before a part is scrapped. Cross-check: the machine "
    "builder's ISO 10791-6 K1/K2 acceptance (tool-to-ball deviation with one rotary and the "
    "linear axes moving together) must not be looser than these; if it is tighter, use it.")


def tolerances() -> dict[str, Any]:
    """The ``tolerances`` section of a demo machine in daemon.yaml."""
    share_um = PART_TOLERANCE_MM * 1e3 * MACHINE_SHARE  # 33 µm
    return {
        "basis": BASIS,
        "default_translation_um": {
            "warn": 15, "fail": 25, "drift_warn": 5, "drift_fail": 10,
            "source": f"1/3 of the {PART_TOLERANCE_MM:g} mm part tolerance ({share_um:.0f} µm) "
                      "less margin: a pivot offset moves the tool tip 1:1"},
        "default_rotation_urad": {
            "warn": 60, "fail": 100, "drift_warn": 20, "drift_fail": 40,
            "source": f"{100e-6 * LEVER_MM * 1e3:.0f} µm at the {LEVER_MM:g} mm lever from the "
                      "rotary axes to the work"},
        "volumetric_max_um": {
            "warn": 20, "fail": 30, "drift_warn": 8, "drift_fail": 15,
            "source": f"the machine's 1/3 share of the {PART_TOLERANCE_MM:g} mm part "
                      f"tolerance ({share_um:.0f} µm), rounded down"},
        "residual_rms_um": 5,
        "run_drift_um": 8,
    }
