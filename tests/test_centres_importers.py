"""Instrument files → centres (contracts/importers): the KinOpt and DMIS fixtures written from
their documentation read back the centres they were written from; format detection; every
refusal names file, line and what was expected."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from contracts.centres_file import CentresFileError
from contracts.importers import CentresImportError, detect, import_centres
from tests.regen_centres_fixtures import (
    DMIS_ROTATION_DEG,
    DMIS_TRANSLATION_MM,
    centres,
    dmis,
    kinopt,
    rotation,
)

DATA = Path(__file__).resolve().parent / "data" / "centres"
BALLS = ["B1", "B2", "B3", "B4"]


@pytest.fixture(scope="module")
def truth():
    return centres()


def test_fixtures_are_what_the_generator_writes(truth) -> None:
    # the committed files are the generator's output: a change to either shows here
    poses, q = truth
    assert (DATA / "kinopt_B1.nc").read_text(encoding="utf-8") == kinopt(poses, q)
    assert (DATA / "dmis_cmm.dmo").read_text(encoding="utf-8") == dmis(poses, q)


def test_kinopt_records_become_centres_of_one_ball(truth) -> None:
    poses, q = truth
    path = DATA / "kinopt_B1.nc"
    assert detect(path) == "kinopt"
    cf = import_centres(path, balls=BALLS, rotary=("B", "C"), ball="B1")
    assert cf.frame == "machine" and len(cf.rows) == len(poses) == 14
    assert {r.ball for r in cf.rows} == {"B1"}
    assert [(r.b_cmd_deg, r.c_cmd_deg) for r in cf.rows] == poses
    assert [r.pose for r in cf.rows] == list(range(14)) and {r.repeat for r in cf.rows} == {0}
    xyz = np.array([[r.x_mm, r.y_mm, r.z_mm] for r in cf.rows])
    np.testing.assert_allclose(xyz, q[:, 0], atol=5e-7)  # six decimals in the program
    assert cf.lines[0] == 16  # the record's first line, for messages


def test_kinopt_refusals_name_the_line() -> None:
    base = (DATA / "kinopt_B1.nc").read_text(encoding="utf-8")

    def err(text: str, **kw) -> str:
        with pytest.raises(CentresImportError) as e:
            import_centres("k.nc", "kinopt", balls=BALLS, rotary=("B", "C"), text=text,
                           **{"ball": "B1", **kw})
        return str(e.value)

    assert "k.nc: line 16: @P1 = V.L.RESULT_V[0] is a variable" in err(
        base.replace("@P1 = -100.068148", "@P1 = V.L.RESULT_V[0]", 1))
    assert "line 16: SysCalibFitAddRecord needs @P1-@P6" in err(
        base.replace("      @P6 = 0          \\  (associated C coordinate)\n", "", 1))
    assert "line 16: A = 5, but the machine has rotary axes B/C" in err(
        base.replace("@P4 = 0 ", "@P4 = 5 ", 1))
    assert "outside" in err(base.replace("@P3 = 152.162135", "@P3 = 1e999", 1))
    assert "a comment '(' is not closed" in err(base.replace("(X coordinate", "(X coord", 1)
                                                .replace("centre point)", "centre point", 1))
    assert "continued past the end of the file" in err(base.rstrip("M30\n") + " \\\n")
    assert "no L CYCLE" in err("; nothing here\nM30\n")
    assert "give the ball with --ball" in err(base, ball=None)
    assert "unknown ball 'B7'" in err(base, ball="B7")
    # the same indexation twice is the next repeat, not a duplicate
    twice = base.replace("M30\n", base[base.index('L CYCLE [NAME = "SysCalibFitAddRecord'):
                                       base.index("#VAR\nV.P.MAX")] + "M30\n")
    cf = import_centres("k.nc", "kinopt", balls=BALLS, rotary=("B", "C"), ball="B1", text=twice)
    assert len(cf.rows) == 28 and {r.repeat for r in cf.rows} == {0, 1}


def test_dmis_spheres_in_the_instrument_frame(truth) -> None:
    poses, q = truth
    path = DATA / "dmis_cmm.dmo"
    assert detect(path) == "dmis"
    cf = import_centres(path, balls=BALLS, rotary=("B", "C"), poses=poses)
    assert cf.frame == "instrument" and "RUMBA THESIS ARTEFACT" in cf.instrument
    assert len(cf.rows) == 56 and [r.ball for r in cf.rows[:4]] == BALLS
    xyz = np.array([[r.x_mm, r.y_mm, r.z_mm] for r in cf.rows]).reshape(14, 4, 3)
    want = q @ rotation(DMIS_ROTATION_DEG).T + np.array(DMIS_TRANSLATION_MM)
    np.testing.assert_allclose(xyz, want, atol=5e-5)  # four decimals, as the CMM prints
    assert cf.lines[0] == 13  # the continued statement starts on line 13


def test_dmis_units_labels_and_refusals(truth) -> None:
    poses, _ = truth
    base = (DATA / "dmis_cmm.dmo").read_text(encoding="utf-8")

    def read(text: str):
        return import_centres("d.dmo", "dmis", balls=BALLS, rotary=("B", "C"), poses=poses,
                              text=text)

    def err(text: str) -> str:
        with pytest.raises(CentresFileError) as e:
            read(text)
        return str(e.value)

    inch = read(base.replace("UNITS/MM,ANGDEC", "UNITS/INCH,ANGDEC"))
    mm = read(base)
    assert inch.rows[1].x_mm == pytest.approx(mm.rows[1].x_mm * 25.4)
    assert "expected UNITS/MM or UNITS/INCH" in err(base.replace("UNITS/MM", "UNITS/FEET"))
    msg = err(base.replace("FA(B2_P0_R0)=", "FA(BALL2)=", 1))
    assert "d.dmo: line 16: feature label 'BALL2': expected <ball>_P<pose>[_R<repeat>]" in msg
    assert "pose 14, but the plan has poses 0..13" in err(
        base.replace("FA(B2_P0_R0)=", "FA(B2_P14_R0)=", 1))
    assert "polar coordinates (POL)" in err(base.replace("OUTER,CART", "OUTER,POL", 1))
    assert "sphere diameter 0 is not positive" in err(base.replace(",25.4000\n", ",0\n", 2))
    dup = base.replace("FA(B2_P0_R0)=", "FA(B1_P0_R0)=", 1)
    assert "line 16: ball B1 pose 0 repeat 0 run dmis duplicates line 13" in err(dup)
    assert "continued past the end" in err(base.replace("ENDFIL\n", "FA(B1_P0_R1)=$\n"))
    assert "no FA(label)=FEAT/SPHERE" in err("DMISMN/'EMPTY',05.2\nENDFIL\n")
    with pytest.raises(CentresImportError, match="give the plan they index with --plan"):
        import_centres("d.dmo", "dmis", balls=BALLS, rotary=("B", "C"), text=base)


def test_detection_and_unknown_formats(tmp_path: Path) -> None:
    p = tmp_path / "x.txt"
    p.write_text("hello\nworld\n", encoding="utf-8")
    with pytest.raises(CentresImportError, match=r"cannot tell the format.*--format"):
        detect(p)
    with pytest.raises(CentresImportError, match="expected one of auto, csv, kinopt, dmis"):
        import_centres(p, "tchpr451", balls=BALLS, rotary=("B", "C"))
    with pytest.raises(CentresImportError, match="cannot read"):
        import_centres(tmp_path / "absent.dmo", "dmis", balls=BALLS, rotary=("B", "C"),
                       poses=[(0.0, 0.0)])
    p.write_bytes(b"\xff\xfe DMISMN/'X'\n")
    with pytest.raises(CentresImportError, match="not UTF-8"):
        detect(p)
