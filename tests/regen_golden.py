"""Regenerate the golden programs (tests/golden/<dialect>.<ext>) after a deliberate change to the
generator or a template: ``make golden`` (= ``python -m tests.regen_golden``). Review the diff."""

from __future__ import annotations

from pathlib import Path

from contracts.setup_files import artefact_from_dict, load_machine, plan_from_dict
from programs.dialects import DIALECTS
from programs.generate import generate
from programs.model import Program
from programs.toolpath import build_program

ROOT = Path(__file__).resolve().parent.parent
GOLDEN = Path(__file__).resolve().parent / "golden"


def golden_setup() -> tuple:
    """A small plan: thesis machine, two balls of the thesis artefact, two poses, one dwell."""
    machine, mf = load_machine(ROOT / "config" / "machines" / "thesis_wcbxfzyt.yaml")
    art = artefact_from_dict({"name": "golden-2ball", "ball_diameter_mm": 25.4,
                              "rod_diameter_mm": 8,
                              "balls": [{"id": "B1", "position_mm": [-100, -80, 152],
                                         "rod_length_mm": 152},
                                        {"id": "B3", "position_mm": [90, 110, 62],
                                         "rod_length_mm": 62}]})
    plan = plan_from_dict({"name": "golden-2poses", "stylus_diameter_mm": 6,
                           "poses": [[0, 0], [30, 60]], "dwell_s": 0.2,
                           "feeds": {"probe_mm_min": 300, "approach_mm_min": 2000}})
    return machine, mf, art, plan


def golden_program() -> Program:
    """The golden plan's tool path (dialect-free)."""
    return build_program(*golden_setup())


def golden_files() -> dict[str, str]:
    """File name → expected text, for every dialect (plus Heidenhain's format files), as
    ``programs.generate`` makes them (checked, rendered, timed)."""
    out = {}
    for name in sorted(DIALECTS):
        g = generate(*golden_setup(), name)
        out[f"{name}.{g.dialect.extension}"] = g.text
        for aux, text in g.aux_files.items():
            out[f"{name}.{aux}"] = text
    # the two-speed touch (plan feeds.fast_probe_mm_min): only linuxcnc renders it, the other
    # dialects keep one speed (their golden would equal the one above)
    machine, mf, art, plan = golden_setup()
    fast = plan.model_copy(update={"feeds": plan.feeds.model_copy(
        update={"fast_probe_mm_min": 1000.0})})
    out["linuxcnc-two-speed.ngc"] = generate(machine, mf, art, fast, "linuxcnc").text
    # a swivel head, a fork head (tilted probe: TCPM off, Heidenhain cycle 4) and a
    # nutating table, one ball at two poses (one tilted) in every dialect
    for family, args in head_family_setups().items():
        for name in sorted(DIALECTS):
            g = generate(*args, name)
            out[f"{family}.{name}.{g.dialect.extension}"] = g.text
            for aux, text in g.aux_files.items():
                out[f"{family}.{name}.{aux}"] = text
    return out


def head_family_setups() -> dict[str, tuple]:
    """(machine, machine file, artefact, plan) of the head families' golden programs."""
    art = artefact_from_dict({"name": "golden-1ball", "ball_diameter_mm": 25.4,
                              "rod_diameter_mm": 8,
                              "balls": [{"id": "B1", "position_mm": [-90, -70, 70],
                                         "rod_length_mm": 120}]})
    out = {}
    for family, machine_file, poses in (("swivelhead", "swivelhead_wcfxyzbt", [[0, 0], [-40, 90]]),
                                        ("forkhead", "forkhead_wxfyzcat", [[0, 0], [30, -90]]),
                                        ("nutating", "nutating_wcbyfxzt", [[0, 0], [80, 90]])):
        machine, mf = load_machine(ROOT / "config" / "machines" / f"{machine_file}.yaml")
        plan = plan_from_dict({"name": f"golden-{family}", "stylus_diameter_mm": 6,
                               "stylus_length_mm": 120 if family != "nutating" else 100,
                               "poses": poses,
                               "feeds": {"probe_mm_min": 300, "approach_mm_min": 2000}})
        out[family] = (machine, mf, art, plan)
    return out


def main() -> None:
    GOLDEN.mkdir(exist_ok=True)
    for name, text in golden_files().items():
        (GOLDEN / name).write_text(text, encoding="ascii")
        print(f"wrote {GOLDEN / name}")


if __name__ == "__main__":
    main()
