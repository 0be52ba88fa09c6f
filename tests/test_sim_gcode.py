"""The G-code executor: every dialect latches exactly at the analytic contact; each controller's
own miss semantics, output lines, alarms and control flow."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.rigs.sim_helpers import TABLE_B2, analytic_contact, truth_with
from simulators.controller import VirtualController
from simulators.gcode import DIALECTS
from tests.sim_programs import program
from tests.waiting import until

POSES = [(0.0, 0.0), (30.0, 60.0), (-45.0, 330.0)]


async def execute(truth, text, dialect, files=None, **kw) -> VirtualController:
    vc = VirtualController(truth, **kw)
    await vc.load_program(text, dialect, files)
    await vc.start()
    await vc.wait_done(30)
    return vc


@pytest.mark.parametrize("dialect", DIALECTS)
async def test_every_latch_is_the_analytic_contact(dialect):
    truth = truth_with(TABLE_B2)
    text, files = program(dialect, truth, POSES)
    vc = await execute(truth, text, dialect, files)
    assert vc.state == "done", vc.alarm
    assert len(vc.touches) == len(POSES) * 4 * 5
    for t in vc.touches:
        assert t.triggered
        b, c = t.latched["B"], t.latched["C"]
        want = analytic_contact(truth, t.start, t.end, b, c, t.ball)
        got = np.array([t.latched[a] for a in "XYZ"])
        assert np.max(np.abs(got - want)) < 1e-6, (dialect, t.seq)
    # The program's own result lines carry the same values (rounded by the dialect).
    lines = [ln.split() for ln in vc.printed if ln.startswith("RUMBA")]
    assert len(lines) == len(vc.touches)
    for f, t in zip(lines, vc.touches, strict=True):
        assert int(f[1]) == t.seq and float(f[6]) == 1.0
        assert abs(float(f[7]) - t.latched["X"]) < 6e-5
        assert abs(float(f[9]) - t.latched["Z"]) < 6e-5


@pytest.mark.parametrize("dialect", DIALECTS)
async def test_a_miss_follows_the_controller(dialect):
    """Ball B1 removed: Fanuc/Haas latch the END point and the program's own check raises
    #3000; LinuxCNC stops on G38.2; Siemens sets $AC_MEA[1]=0 and SETAL; Heidenhain errors."""
    truth = truth_with({"absent_balls": ["B1"]})
    text, files = program(dialect, truth, [(0.0, 0.0)], balls=[0])
    vc = await execute(truth, text, dialect, files)
    assert vc.state == "alarm"
    expect = {"fanuc": "3001", "haas": "3001", "linuxcnc": "G38.2 move finished",
              "siemens": "SETAL 65000", "heidenhain": "TOUCH POINT INACCESSIBLE"}[dialect]
    assert expect in vc.alarm
    assert len(vc.touches) == 1 and not vc.touches[0].triggered
    if dialect in ("fanuc", "haas"):
        end = vc.touches[0].end
        assert vc.variables["#5061"] == pytest.approx(end[0], abs=1e-12)
        assert vc.variables["#605"] == 0.0
        assert vc.printed[-1].split()[6] == "0"  # trig 0 printed before the alarm
    if dialect == "linuxcnc":
        assert vc.variables["#5070"] == 0.0
    if dialect == "siemens":
        assert vc.variables["R105"] == 0.0


async def test_fanuc_macro_flow_and_dprnt_format():
    truth = truth_with({})
    text = "\n".join([
        "%", "O0001", "#100=0", "#101=0",
        "WHILE[#100LT5]DO1", "#101=#101+[#100*2]", "#100=#100+1", "END1",
        "IF[#101EQ20]GOTO50", "#3000=7(NOT REACHED)",
        "N50 #102=-3.14159", "#103=SQRT[16]+ATAN[1]/[1]",
        "DPRNT[V*#101[30]*#102[54]*#103[32]]", "M30", "%"])
    vc = await execute(truth, text, "fanuc")
    assert vc.state == "done", vc.alarm
    assert vc.variables["#103"] == pytest.approx(49.0)
    assert vc.printed == ["V 20 -3.1416 49.00"]


async def test_fanuc_alarm_text_and_unknown_gcode():
    truth = truth_with({})
    vc = await execute(truth, "%\nG21\nG05.1 Q1\nM30\n%\n", "fanuc")
    assert vc.state == "alarm" and "G5.1" in vc.alarm
    vc = await execute(truth, "%\n#1=2\nIF[#1GT1]THEN#3000=5(BAD THING)\nM30\n%\n", "fanuc")
    assert vc.alarm == "#3000 alarm 3005 BAD THING (line 3: IF[#1GT1]THEN#3000=5(BAD THING))"


async def test_linuxcnc_oword_if_else_while_and_named_params():
    truth = truth_with({})
    text = "\n".join([
        "%", "#<n> = 0", "#<acc> = 0",
        "o100 while [#<n> LT 4]", "#<acc> = [#<acc> + #<n> ** 2]", "#<n> = [#<n> + 1]",
        "o100 endwhile",
        "o200 if [#<acc> EQ 99]", "(LOG,wrong)", "o200 elseif [#<acc> EQ 14]",
        "(LOG,acc=#<acc>)", "o200 else", "(LOG,wrong too)", "o200 endif", "M2", "%"])
    vc = await execute(truth, text, "linuxcnc")
    assert vc.state == "done", vc.alarm
    assert vc.printed == ["acc=14.000000"]


async def test_siemens_if_else_while_gotof_and_write():
    truth = truth_with({})
    text = "\n".join([
        "DEF INT RERR", "DEF STRING[200] RLINE", "DEF REAL K=2.5", "R1=0",
        "WHILE R1<3", "R1=R1+1", "ENDWHILE",
        "IF R1==3", "RLINE=\"R1 \"<<R1<<\" K \"<<K", "ELSE", "RLINE=\"WRONG\"", "ENDIF",
        "IF R1>2 GOTOF SKIP", "SETAL(61000)", "SKIP:", "WRITE(RERR,\"F\",RLINE)", "M30"])
    vc = await execute(truth, text, "siemens")
    assert vc.state == "done", vc.alarm
    assert vc.printed == ["R1 3 K 2.5"]


async def test_heidenhain_fn_jumps_fprint_and_fn14():
    truth = truth_with({})
    fmt = {"F.A": '"VAL %.0LF %.3LF\\n", Q1, Q2;'}
    text = "\n".join(f"{i} {s}" for i, s in enumerate([
        "BEGIN PGM T MM", "Q1 = +3", "Q2 = SQRT(Q1 * 12) + (SGN(Q1 - 5) + 1) / 2",
        "FN 16: F-PRINT F.A / OUT.TXT", "FN 12: IF +Q1 LT +5 GOTO LBL 99", "M30",
        "LBL 99", "FN 14: ERROR = 1", "LBL 0", "END PGM T MM"]))
    vc = await execute(truth, text, "heidenhain", fmt)
    assert vc.printed == ["VAL 3 6.000"]
    assert vc.state == "alarm" and "FN 14 error 1" in vc.alarm


async def test_heidenhain_preposition_is_approached_at_fmax():
    """Cycle 0/1 go to the programmed point at FMAX first: a point ON the expected contact
    makes the stylus run into the ball when the ball is a few tenths off nominal."""
    truth = truth_with({"setup": {"balls_um": {"B1": [-300, -300, 0]}}})
    from tests.sim_programs import touch_moves

    _, _, end = touch_moves(truth, 0.0, 0.0, 0, 1, overtravel=0.0)
    text = "\n".join(f"{i} {s}" for i, s in enumerate([
        "BEGIN PGM T MM", f"L Z+{end[2] + 60:.4f} R0 FMAX",
        f"L X{end[0] - 5:+.4f} Y{end[1] - 5:+.4f} R0 FMAX", f"L Z{end[2]:+.4f} R0 FMAX",
        "TCH PROBE 1.0 POLAR DATUM PLANE", "TCH PROBE 1.1 X ANGLE: +45.0000",
        f"TCH PROBE 1.2 X{end[0]:+.4f} Y{end[1]:+.4f} Z{end[2]:+.4f}",
        "END PGM T MM"]))
    vc = await execute(truth, text, "heidenhain")
    assert vc.state == "alarm" and "COLLISION" in vc.alarm


async def test_overtravel_and_feed_limits_alarm():
    truth = truth_with({})
    vc = await execute(truth, "%\nG00 X900.\nM30\n%\n", "fanuc")
    assert vc.state == "alarm" and "OVERTRAVEL X" in vc.alarm
    vc = await execute(truth, "%\nG00 Z300.\nG31 Z290. F5000.\nM30\n%\n", "fanuc")
    assert vc.state == "alarm" and "probing feed" in vc.alarm


GENERATED = list(DIALECTS)


@pytest.fixture(scope="module")
def generated():
    from contracts.setup_files import plan_from_dict
    from programs.toolpath import build_program

    truth = truth_with(TABLE_B2)
    plan = plan_from_dict({"name": "t", "stylus_diameter_mm": 6,
                           "poses": [[0, 0], [30, 60], [-45, 330]]})
    return truth, build_program(truth.machine, truth.machine_file, truth.artefact, plan)


@pytest.mark.parametrize("dialect", GENERATED)
async def test_generated_programs_latch_exactly(dialect, generated):
    """What programs/ (tool path + dialects) emits runs to the end on the simulator, and
    every latch is the analytic contact (link and setup errors on, no noise, no effects)."""
    from programs.dialects import get_dialect

    truth, prog = generated
    dia = get_dialect(dialect)
    vc = await execute(truth, dia.render(prog), dialect, dia.aux_files(prog))
    assert vc.state == "done", vc.alarm
    assert len(vc.touches) == len(prog.touches) == 3 * 4 * 5
    for t in vc.touches:
        want = analytic_contact(truth, t.start, t.end, t.latched["B"], t.latched["C"], t.ball)
        got = np.array([t.latched[a] for a in "XYZ"])
        assert t.triggered and np.max(np.abs(got - want)) < 1e-6, (dialect, t.seq)
    # The daemon's own result-line parser reads every line the controller printed.
    bound = dia.bind(prog)
    hits = [h for h in (bound.parse_result(ln) for ln in vc.printed) if h is not None]
    assert [h.seq for h in hits] == [t.seq for t in vc.touches]
    for h, t in zip(hits, vc.touches, strict=True):
        assert h.triggered and abs(h.axes["X"] - t.latched["X"]) < 6e-5



@pytest.mark.parametrize("dialect,stop", [("fanuc", "M00"), ("fanuc", "#3006=1(CHECK)"),
                                          ("siemens", "M0"), ("linuxcnc", "M0")])
async def test_program_stop_holds_until_cycle_start(dialect, stop):
    truth = truth_with({})
    end = "M30" if dialect != "linuxcnc" else "M2"
    vc = VirtualController(truth)
    await vc.load_program(f"G0 Z300.\n{stop}\nG0 Z310.\n{end}\n", dialect)
    await vc.start()
    await until(lambda: vc.state == "hold", 10, "the program stop")
    assert vc.position()["Z"] == 300.0
    await vc.start()
    assert await vc.wait_done(5) == "done" and vc.position()["Z"] == 310.0


async def test_heidenhain_fn18_reads_the_last_touch_point():
    truth = truth_with({})
    qn = truth.centre_ctrl(0, 0.0, 0.0, nominal=True)
    text = "\n".join(f"{i} {s}" for i, s in enumerate([
        "BEGIN PGM T MM", f"L Z{qn[2] + 60:+.4f} R0 FMAX",
        f"L X{qn[0]:+.4f} Y{qn[1]:+.4f} R0 FMAX",
        "TCH PROBE 0.0 REF. PLANE Q9 Z-",
        f"TCH PROBE 0.1 X{qn[0]:+.4f} Y{qn[1]:+.4f} Z{qn[2] + 17.7:+.4f}",
        "FN 18: SYSREAD Q1 = ID360 NR1 IDX3", "FN 18: SYSREAD Q2 = ID360 NR2 IDX3",
        "END PGM T MM"]))
    vc = await execute(truth, text, "heidenhain")
    assert vc.state == "done", vc.alarm
    assert vc.variables["Q2"] == pytest.approx(qn[2] + 15.7, abs=1e-9)  # stylus centre
    assert vc.variables["Q9"] == vc.variables["Q117"] == vc.variables["Q2"]
    assert vc.variables["Q1"] == pytest.approx(qn[2] + 12.7, abs=1e-9)  # surface point
