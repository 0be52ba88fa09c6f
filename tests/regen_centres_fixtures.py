"""Regenerate the instrument-file fixtures of the centres importers:
`python -m tests.regen_centres_fixtures`.

Both are written from the formats' documentation (each file's header names it) with centres
from a known truth: the thesis machine (WCBXFZYT) with the Table B.2 link errors (METHOD.md §5),
setup errors of a few hundred µm, the annex-B poses, 0.5 µm centre noise (fixed seed):

* ``kinopt_B1.nc``: ball B1 alone (a KinOpt program measures one sphere), machine frame;
* ``dmis_cmm.dmo``: the four balls seen by a CMM whose frame is turned (20°, −35°, 110° about
  x, y, z) and shifted (500, −200, 30 mm) from the machine axes — ``DMIS_ROTATION_DEG``,
  ``DMIS_TRANSLATION_MM`` — written with four decimals as a CMM prints them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from contracts.setup_files import load_artefact, load_machine, load_plan
from simulators.exact_log import THESIS_LINKS_UM_URAD, Truth, to_internal, true_centres

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "tests" / "data" / "centres"
BALL_SETUP_UM = [[120.0, -240.0, 310.0], [-180.0, 90.0, -150.0],
                 [260.0, 140.0, 80.0], [-70.0, -310.0, 200.0]]
PROBE_SETUP_UM = [85.0, -40.0, 150.0]
NOISE_UM = 0.5
DMIS_ROTATION_DEG = (20.0, -35.0, 110.0)
DMIS_TRANSLATION_MM = (500.0, -200.0, 30.0)
KINOPT_DOC = "infosys.beckhoff.com/content/1033/tf5245_tc3_cnc_cycles_kinopt/326272267.html"


def rotation(deg: tuple[float, float, float]) -> np.ndarray:
    """Rot_x · Rot_y · Rot_z of the angles (°)."""
    out = np.eye(3)
    for k, a in enumerate(np.radians(deg)):
        c, s = np.cos(a), np.sin(a)
        i, j = [(1, 2), (2, 0), (0, 1)][k]
        r = np.eye(3)
        r[i, i] = r[j, j] = c
        r[i, j], r[j, i] = -s, s
        out = out @ r
    return out


def centres() -> tuple[list[tuple[float, float]], np.ndarray]:
    machine, _ = load_machine(ROOT / "config/machines/thesis_wcbxfzyt.yaml")
    artefact = load_artefact(ROOT / "config/artefacts/thesis_4ball.yaml")
    plan = load_plan(ROOT / "config/plans/thesis_annexB_14poses.yaml")
    poses = [(p.b_deg, p.c_deg) for p in plan.poses]
    truth = Truth(to_internal(THESIS_LINKS_UM_URAD), np.array(BALL_SETUP_UM) * 1e-3,
                  np.array(PROBE_SETUP_UM) * 1e-3)
    q = true_centres(machine, artefact, poses, truth)
    rng = np.random.default_rng(451)
    return poses, q + rng.normal(0.0, NOISE_UM * 1e-3, q.shape)


def kinopt(poses: list[tuple[float, float]], q: np.ndarray) -> str:
    out = ["; Kinematics optimisation with sphere centres measured beforehand (rumba-cnc test",
           "; fixture, tests/regen_centres_fixtures.py). Format: Beckhoff TwinCAT CNC TF5245,",
           f'; "Sphere centre points already calculated", {KINOPT_DOC}',
           "; Ball B1 of the thesis artefact, annex-B poses; A is absent on this B/C machine.",
           "#VAR", "V.L.KIN_TYP = 80        (kinematic measured)",
           "V.L.KIN_VARIANT = 0     (variant of kinematic measured)",
           f"V.L.NUMBER_OF_POSES = {len(poses)} (number of measurement poses)", "#ENDVAR",
           'L CYCLE [NAME = "SysCalibFitInit.ecy"     \\',
           "        @P1 = V.L.KIN_TYP                 \\",
           "        @P2 = V.L.KIN_VARIANT             \\",
           "        @P3 = V.L.NUMBER_OF_POSES         \\", "        ]",
           "; Call cycle to add new measurement data"]
    for (b, c), x in zip(poses, q[:, 0], strict=True):
        out += ['L CYCLE [NAME = "SysCalibFitAddRecord.ecy" \\',
                f"      @P1 = {x[0]:.6f} \\  (X coordinate of centre point)",
                f"      @P2 = {x[1]:.6f} \\  (Y coordinate of centre point)",
                f"      @P3 = {x[2]:.6f} \\  (Z coordinate of centre point)",
                "      @P4 = 0          \\  (associated A coordinate)",
                f"      @P5 = {b:g}          \\  (associated B coordinate)",
                f"      @P6 = {c:g}          \\  (associated C coordinate)", "      ]"]
    out += ["#VAR", "V.P.MAX_PRECISION = 0.06   (precision)",
            "V.P.LIST_FORMAT   = 1      (list format for result)", "#ENDVAR",
            'L CYCLE [NAME = "SysCalibFit.ecy"   \\', "        @P1 = V.P.LIST_FORMAT       \\",
            "        @P2 = V.P.MAX_PRECISION     \\", "        ]", "M30"]
    return "\n".join(out) + "\n"


def dmis(poses: list[tuple[float, float]], q: np.ndarray) -> str:
    r, t = rotation(DMIS_ROTATION_DEG), np.array(DMIS_TRANSLATION_MM)
    m = q @ r.T + t
    out = ["$$ DMIS results of the thesis 4-ball artefact measured on a CMM at the 14 annex-B",
           "$$ indexations of its positioner (rumba-cnc test fixture, written by",
           "$$ tests/regen_centres_fixtures.py). Format: ANSI/DMIS 105.2 output statements as in",
           "$$ the DMSC QIF -> DMIS results example (FILNAM, $$ comments, UNITS/MM,ANGDEC,",
           "$$ OUTPUT/FA(..), FA(label)=FEAT/..); labels <ball>_P<pose>_R<repeat>.",
           "DMISMN/'RUMBA THESIS ARTEFACT',05.2", "FILNAM/'THESIS_4BALL_CMM',05.2",
           "UNITS/MM,ANGDEC",
           "$$ datum plane of the fixture (not a sphere: skipped by the importer)",
           "OUTPUT/FA(DAT_A)",
           "FA(DAT_A)=FEAT/PLANE,CART,0.0000,0.0000,0.0000,0.0000,0.0000,1.0000"]
    for i in range(len(poses)):
        for j, ball in enumerate(("B1", "B2", "B3", "B4")):
            lab = f"{ball}_P{i}_R0"
            x, y, z = m[i, j]
            out.append(f"OUTPUT/FA({lab})")
            if (i, j) == (0, 0):  # one statement continued over two lines ($)
                out += [f"FA({lab})=FEAT/SPHERE,OUTER,CART,{x:.4f},$", f"{y:.4f},{z:.4f},25.4000"]
            else:
                out.append(f"FA({lab})=FEAT/SPHERE,OUTER,CART,{x:.4f},{y:.4f},{z:.4f},25.4000")
    out.append("ENDFIL")
    return "\n".join(out) + "\n"


def main() -> None:
    poses, q = centres()
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "kinopt_B1.nc").write_text(kinopt(poses, q), encoding="utf-8")
    (OUT / "dmis_cmm.dmo").write_text(dmis(poses, q), encoding="utf-8")
    print(f"wrote {OUT / 'kinopt_B1.nc'} and {OUT / 'dmis_cmm.dmo'}")


if __name__ == "__main__":
    main()
