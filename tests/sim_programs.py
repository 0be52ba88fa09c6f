"""Hand-rolled probing programs for simulator tests, in each dialect's emitted subset
(gcode_templates/*/README.md), independent of programs/toolpath.py: the nominal touch geometry,
a simple safe path (retract, index, descend beside the ball, feed, probe, retract)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from contracts.messages import TOUCH_DIRECTIONS
from simulators.truth import TruthModel

_CENTRES: dict = {}


def _centre(truth: TruthModel, ball: int, b: float, c: float) -> np.ndarray:
    key = (id(truth), ball, b, c)
    if key not in _CENTRES:
        _CENTRES[key] = (truth, truth.centre_ctrl(ball, b, c, nominal=True))
    return _CENTRES[key][1]


def touch_moves(truth: TruthModel, b: float, c: float, ball: int, touch: int,
                standoff: float = 2.0, overtravel: float = 2.0, gap: float = 3.0
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(clearance, start, end) controller X Y Z of one touch on the NOMINAL machine."""
    qc = _centre(truth, ball, b, c)
    # Controller → relative (tip − ball) is affine; controller X Y Z = relative + centre here
    # for the machines we test (signs make controller axes the tool motion).
    d = np.asarray(TOUCH_DIRECTIONS[touch])
    rho = truth.artefact.balls[ball].diameter_mm / 2 + truth.errors.probe.stylus_diameter_mm / 2
    return (qc - d * (rho + standoff + gap), qc - d * (rho + standoff),
            qc - d * (rho - overtravel))


def _f(v: float, signed: bool = False) -> str:
    return f"{v:+.4f}" if signed else f"{v:.4f}"


def program(dialect: str, truth: TruthModel, poses: Sequence[tuple[float, float]],
            balls: Sequence[int] | None = None, feed: float = 300.0,
            standoff: float = 2.0, overtravel: float = 2.0) -> tuple[str, dict[str, str]]:
    """A complete program text and its auxiliary files."""
    r1, r2 = truth.rotary_letters
    balls = list(range(len(truth.artefact.balls))) if balls is None else list(balls)
    safe_z = 0.0
    for b, c in poses:
        for i in balls:
            safe_z = max(safe_z, _centre(truth, i, b, c)[2] + 40.0)
    out: list[str] = []
    files: dict[str, str] = {}
    h = dialect == "heidenhain"
    s = dialect == "siemens"
    lc = dialect == "linuxcnc"

    def rapid(**ax: float) -> None:
        if h:
            out.append("L " + " ".join(f"{k}{_f(v, True)}" for k, v in ax.items()) + " R0 FMAX")
        else:
            out.append(("G0 " if lc or s else "G00 ")
                       + " ".join(f"{k}{_f(v)}" for k, v in ax.items()))

    def feedto(p: np.ndarray, f: float) -> None:
        if h:
            out.append(f"L X{_f(p[0], True)} Y{_f(p[1], True)} Z{_f(p[2], True)} R0 F{f:g}")
        else:
            out.append(f"{'G1' if lc or s else 'G01'} X{_f(p[0])} Y{_f(p[1])} Z{_f(p[2])} "
                       f"F{f:.1f}")

    if h:
        out.append("BEGIN PGM RUMBA MM")
        out.append("Q1599 = +0")
    elif s:
        out += ["DEF INT RERR", "DEF STRING[200] RLINE", "G71 G90 G17 G94 G40", "R99=0"]
    elif lc:
        out += ["%", "(LOGOPEN,rumba_results.log)", "G21 G90 G17 G94 G40 G80", "#3999 = 0"]
    else:
        out += ["%", "O9100 (RUMBA TEST)", "G21 G90 G17 G94 G40 G80", "POPEN", "#599=0"]
    seq = 0
    for ip, (b, c) in enumerate(poses):
        rapid(Z=safe_z)
        rapid(**{r1: b, r2: c})
        for i in balls:
            bid = truth.artefact.balls[i].id
            for k in range(1, 6):
                seq += 1
                clear, start, end = touch_moves(truth, b, c, i, k, standoff, overtravel)
                rapid(X=clear[0], Y=clear[1])
                rapid(Z=clear[2])
                feedto(start, 2000.0)
                pre = f"RUMBA {seq} 0 {ip} {bid} {k}"
                if h:
                    if k == 5:
                        out += ["TCH PROBE 0.0 REF. PLANE Q1579 Z-",
                                f"TCH PROBE 0.1 X{_f(start[0], True)} Y{_f(start[1], True)} "
                                f"Z{_f(start[2], True)}"]
                    else:
                        ang = np.degrees(np.arctan2(*TOUCH_DIRECTIONS[k][1::-1]))
                        out += ["TCH PROBE 1.0 POLAR DATUM PLANE",
                                f"TCH PROBE 1.1 X ANGLE: {ang:+.4f}",
                                f"TCH PROBE 1.2 X{_f(start[0], True)} Y{_f(start[1], True)} "
                                f"Z{_f(start[2], True)}"]
                    out += [f"Q1580 = +{seq}", "Q1586 = Q115", "Q1587 = Q116", "Q1588 = Q117",
                            "Q1589 = Q118", "Q1590 = Q119", "Q1585 = +1",
                            f"FN 16: F-PRINT RUMBA_{bid}.A / RUMBA_RES.TXT", f"Q1599 = +{seq}"]
                    files[f"RUMBA_{bid}.A"] = (
                        f'"RUMBA %.0LF 0 {ip} {bid} {k} %.0LF %.4LF %.4LF %.4LF %.4LF %.4LF'
                        '\\n", Q1580, Q1585, Q1586, Q1587, Q1588, Q1589, Q1590;')
                elif s:
                    out += [f"MEAS=1 G1 X{_f(end[0])} Y{_f(end[1])} Z{_f(end[2])} F{feed:.1f}",
                            "STOPRE", "R105=$AC_MEA[1]", "R106=$AA_MW[X]", "R107=$AA_MW[Y]",
                            "R108=$AA_MW[Z]", f"R109=$AA_IW[{r1}]", f"R110=$AA_IW[{r2}]",
                            f'RLINE="{pre} "<<R105<<" "<<R106<<" "<<R107<<" "<<R108<<" "<<R109'
                            '<<" "<<R110', 'WRITE(RERR,"RUMBA_RES",RLINE)', f"R99={seq}",
                            "IF R105==0", f'MSG("RUMBA PROBE MISS SEQ {seq}")', "SETAL(65000)",
                            "M0", "ENDIF"]
                elif lc:
                    out += [f"G38.2 X{_f(end[0])} Y{_f(end[1])} Z{_f(end[2])} F{feed:.1f}",
                            "#4005 = #5070", f"#3999 = {seq}",
                            f"(LOG,{pre} #5070 #5061 #5062 #5063 #5065 #5066)",
                            f"o{10000 + seq} if [[#5070 EQ 0] AND [#<_task> EQ 1]]",
                            f"(abort,RUMBA probe miss seq {seq})", f"o{10000 + seq} endif"]
                else:
                    out += [f"#2={_f(end[0])}", f"#3={_f(end[1])}", f"#4={_f(end[2])}",
                            f"G31 X{_f(end[0])} Y{_f(end[1])} Z{_f(end[2])} F{feed:.1f}",
                            "#1=ABS[#5061-#2]+ABS[#5062-#3]+ABS[#5063-#4]",
                            "#605=1.", "IF[#1LT0.001]THEN#605=0.",
                            "#606=#5061", "#607=#5062", "#608=#5063", "#609=#5064",
                            "#610=#5065", f"#599={seq}",
                            f"DPRNT[{pre.replace(' ', '*')}*#605[10]*#606[54]*#607[54]"
                            "*#608[54]*#609[54]*#610[54]]",
                            f"IF[#605EQ0]THEN#3000=1(RUMBA MISS SEQ {seq})"]
                rapid(X=clear[0], Y=clear[1], Z=clear[2])
                rapid(Z=safe_z)
    rapid(Z=safe_z)
    if h:
        out += ["M30", "END PGM RUMBA MM"]
        out = [f"{n} {line}" for n, line in enumerate(out)]
    elif s:
        out.append("M30")
    elif lc:
        out += ["(LOGCLOSE)", "M2", "%"]
    else:
        out += ["PCLOS", "M30", "%"]
    return "\n".join(out) + "\n", files
