"""Dialects: the result-line grammar (print capture), result slots (variable capture), identity
checks, sanitising, and the per-dialect constructs every touch carries (probe word, miss check)."""

from __future__ import annotations

import re

import pytest

from contracts.setup_files import artefact_from_dict
from contracts.yaml_files import ConfigError
from programs.dialects import DIALECTS, Fanuc, get_dialect, safe_text
from programs.geometry import ProgramError
from programs.toolpath import build_program
from tests.regen_golden import golden_program

PROG = golden_program()
N = len(PROG.touches)


@pytest.mark.parametrize("line, trig, xyz", [
    ("RUMBA 7 0 1 B3 2 1 -12.5000 3.2500 140.1000 30.0000 60.0000", True,
     (-12.5, 3.25, 140.1)),
    # Fanuc DPRNT: '*' printed as space, numbers padded, leading '-.'
    ("  RUMBA   7  0  1  B3  2    1     -.5000     3.2500   140.1000    30.0000    60.0000\r\n",
     True, (-0.5, 3.25, 140.1)),
    # LinuxCNC LOG prints %f
    ("RUMBA 7 0 1 B3 2 0.000000 -12.500000 3.250000 140.100000 30.000000 60.000000", False,
     (-12.5, 3.25, 140.1)),
    # Siemens << conversion of REAL
    ("RUMBA 7 0 1 B3 2 1 -12.5 3.25 140.1 30 60\t", True, (-12.5, 3.25, 140.1)),
])
def test_parse_result_grammar(line, trig, xyz):
    hit = get_dialect("linuxcnc").parse_result(line)
    assert (hit.seq, hit.repeat, hit.pose, hit.ball, hit.touch) == (7, 0, 1, "B3", 2)
    assert hit.triggered is trig
    assert (hit.axes["X"], hit.axes["Y"], hit.axes["Z"]) == xyz
    assert (hit.axes["b"], hit.axes["c"]) == (30.0, 60.0)


def test_parse_result_ignores_other_output_and_rejects_broken_lines():
    d = get_dialect("fanuc")
    assert d.parse_result("PROGRAM START") is None
    assert d.parse_result("") is None
    with pytest.raises(ValueError, match="does not match the grammar"):
        d.parse_result("RUMBA 7 0 1 B3 2 1 -12.5 3.25")  # truncated line
    with pytest.raises(ValueError):
        d.parse_result("RUMBA 7 0 1 B3 6 1 1 2 3 4 5")  # touch 6 does not exist


@pytest.mark.parametrize("name", sorted(DIALECTS))
@pytest.mark.parametrize(("line", "match"), [
    # non-ASCII digits and spaces: Python's \d and \s take them unless the grammar is ASCII
    ("RUMBA 1 0 0 B1 1 1.0000 -111.1697 -91.2982 152.1619 0.0000 \u0663", "grammar"),
    ("RUMBA \u0661 0 0 B1 1 1 1 2 3 4 5", "grammar"),
    ("RUMBA 1 0 0 B1 1 1 1\u00a02 3 4 5 6", "grammar"),
    ("RUMBA 1 0 0 B1 1 1 1\u20282 3 4 5 6", "grammar"),
    # plausibility: a garbled line must not reach the journal as a position
    ("RUMBA 1 0 0 B1 1 1 1 2 " + "9" * 300 + " 4 5", "beyond"),
    ("RUMBA 1 0 0 B1 1 1 1 2 3 100001 5", "beyond"),
    ("RUMBA 1 0 0 B1 1 7 1 2 3 4 5", "neither 0 nor 1"),
    ("RUMBA 1 0 0 B1 1 0.5 1 2 3 4 5", "neither 0 nor 1"),
])
def test_parse_result_refuses_non_ascii_and_implausible_values(name, line, match):
    with pytest.raises(ValueError, match=match):
        get_dialect(name).parse_result(line)


def test_bound_parser_checks_identity_and_fills_the_program_side():
    t = PROG.touches[6]
    bound = get_dialect("siemens").bind(PROG)
    line = (f"RUMBA {t.id.seq} {t.id.repeat} {t.id.pose} {t.id.ball} {t.id.touch} 1 "
            "1 2 3 30 60")
    hit = bound.parse_result(line)
    assert hit.axes == {"X": 1.0, "Y": 2.0, "Z": 3.0, "B": 30.0, "C": 60.0}
    assert (hit.b_cmd_deg, hit.c_cmd_deg) == (t.b_deg, t.c_deg)
    assert hit.direction == t.direction and hit.feed_mm_min == 300
    wrong = line.replace(f" {t.id.ball} ", " B9 ", 1)
    with pytest.raises(ValueError, match=f"touch seq {t.id.seq} reported as .* ball B9"):
        bound.parse_result(wrong)
    with pytest.raises(ValueError, match="touch seq 999, not in the program"):
        bound.parse_result("RUMBA 999 0 0 B1 1 1 1 2 3 0 0")


@pytest.mark.parametrize("name", sorted(DIALECTS))
def test_every_touch_carries_identity_probe_and_miss_check(name):
    d = get_dialect(name)
    text = d.render(PROG)
    probe = {"fanuc": r"\bG31 X", "siemens": r"MEAS=1 G1 X", "linuxcnc": r"\bG38\.2 X",
             "heidenhain": r"TCH PROBE [01]\.0 "}[name]
    assert len(re.findall(probe, text)) == N
    miss = {"fanuc": r"IF\[#\d+EQ0\]THEN#3000=1\(RUMBA MISS SEQ \d+\)",
            "siemens": r"IF R\d+==0\nMSG\(\"RUMBA PROBE MISS SEQ \d+ .*\"\)\nSETAL\(65000\)",
            "linuxcnc": r"o\d+ if \[\[#5070 EQ 0\] AND \[#<_task> EQ 1\]\]\n\(abort,",
            "heidenhain": r"FN 12: IF \+Q\d+ LT \+0\.5 GOTO LBL 99"}[name]
    assert len(re.findall(miss, text)) == N
    for t in PROG.touches:  # the identity of every touch is in its result line
        ident = f"{t.id.seq} {t.id.repeat} {t.id.pose} {t.id.ball} {t.id.touch}"
        if name == "fanuc":
            assert f"DPRNT[RUMBA*{ident.replace(' ', '*')}*" in text
        elif name == "heidenhain":
            assert f"{d.slot_address(t.id.seq, 0)} = +{t.id.seq}\n" in re.sub(r"^\d+ ", "",
                                                                                text, flags=re.M)
        else:
            assert f"RUMBA {ident} " in text
    # the counter is written after the slot, once per touch
    assert len(re.findall(re.escape(d.counter) + r" ?= ?\+?[1-9]", text)) == N


def test_slot_addresses_form_a_ring():
    d = get_dialect("fanuc")
    assert d.counter == "#599"
    assert d.slot_address(1, 0) == "#600" and d.slot_address(1, "r2") == "#610"
    assert d.slot_address(9, "seq") == "#600" and d.slot_address(8, "trig") == "#682"
    assert get_dialect("siemens").slot_address(2, "x") == "R117"
    assert get_dialect("heidenhain").slot_address(3, 3) == "Q1625"
    assert get_dialect("linuxcnc").slot_address(1, "trig") == "#4005"


def test_fanuc_haas_reads_rotary_skip_by_letter():
    fanuc = Fanuc().render(PROG)
    haas = get_dialect("haas").render(PROG)
    assert "=#5064\n" in fanuc and "=#5066\n" not in fanuc  # 4th/5th axis
    assert "=#5065\n" in haas and "=#5066\n" in haas  # B and C


def test_sanitiser_blocks_injection():
    for bad in ("B1)\nM30", "B1 (x)", "B1;G0", 'B1"', "B1\r", "B1#3000=1", "ÄB"):
        with pytest.raises(ProgramError):
            safe_text(bad)
    assert safe_text("POSE 3 B -30 C 240") == "POSE 3 B -30 C 240"
    # names are refused at load time already
    with pytest.raises(ConfigError, match=r"balls\.0\.id"):
        artefact_from_dict({"name": "a", "balls": [{"id": "B1)(M30", "position_mm": [0, 0, 50],
                                                   "rod_length_mm": 50}]})


def test_fanuc_refuses_ball_ids_it_cannot_print():
    prog = golden_program()
    prog.artefact = artefact_from_dict({"name": "a", "balls": [
        {"id": b.id.lower(), "position_mm": list(b.position_mm),
         "rod_length_mm": b.rod_length_mm} for b in prog.artefact.balls]})
    prog = build_program(prog.machine, prog.machine_file, prog.artefact, prog.plan)
    with pytest.raises(ProgramError, match="fanuc dialect needs"):
        get_dialect("fanuc").render(prog)
    assert "RUMBA 1 0 0 b1 " in get_dialect("linuxcnc").render(prog)


def test_unknown_dialect():
    with pytest.raises(ProgramError, match="unknown dialect 'okuma'"):
        get_dialect("okuma")


@pytest.mark.parametrize("name", sorted(DIALECTS))
def test_a_config_string_that_bypassed_validation_cannot_reach_the_program(name):
    prog = golden_program()
    prog.plan = prog.plan.model_copy(update={"name": "x)\nM30\n(y"})
    with pytest.raises(ProgramError, match="not allowed in a program"):
        get_dialect(name).render(prog)
