"""Controller dialects: render a ``Program`` with gcode_templates/<dialect>/program.j2 and tell a
driver how the results come back (result-line parser, result-slot variables).

Result line (print capture; DPRNT, WRITE, FN 16 F-PRINT, LinuxCNC LOG), the same in every
dialect, whitespace separated (one or more spaces or tabs, leading spaces allowed, CR LF or LF)::

    RUMBA <seq> <rep> <pose> <ball> <touch> <trig> <x> <y> <z> <r1> <r2>

``seq`` 1-based running touch number, ``rep`` 0-based repeat, ``pose`` 0-based pose index,
``ball`` the ball id (config.SAFE_NAME), ``touch`` 1-4 equator diagonals / 5 pole, ``trig`` 1 when
the probe triggered and 0 when not (a number: ``1``, ``1.``, ``1.000000``), ``x y z`` latched
controller mm, ``r1 r2`` latched first / second rotary axis (alphabetical letters), deg; numbers
are ``[+-]?digits[.digits]`` (Fanuc may print ``-.5`` or pad with spaces). A miss prints its line
with trig 0 and then stops the program with an alarm.

Result slots (variable capture): a ring of ``RING_SLOTS`` slots × ``SLOT_FIELDS`` values plus a
counter; per touch the program writes slot ``(seq-1) % 8`` fields 0 seq, 1 rep, 2 pose, 3 ball
number (1-based, artefact order), 4 touch, 5 trig, 6 X, 7 Y, 8 Z, 9 r1, 10 r2, then the counter =
seq. Addresses per dialect: ``Dialect.counter`` and ``Dialect.slot_address(seq, field)``.
Every construct each dialect emits is listed in gcode_templates/<dialect>/README.md.

Verdict write-back by program (serial DNC): ``Dialect.verdict_program(code)`` is a three-block
program setting the dialect's ``verdict_variable`` (fanuc #598, siemens R4, heidenhain Q1598,
linuxcnc #3998) to 1 PASS, 2 WARN, 3 FAIL or 4 ERROR; the CNC's start-of-shift macro clears it to
0 before printing its request line ``RUMBA REQUEST <machine>`` (read by
``drivers.serial_dnc.parse_request``) and waits for
it to become non-zero.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import jinja2

from contracts.messages import TOUCH_DIRECTIONS, ProbeHit
from contracts.setup_files import SAFE_NAME
from programs.cycletime import estimate
from programs.toolpath import Move, Program, ProgramError, Touch

TEMPLATES = Path(__file__).resolve().parent.parent / "gcode_templates"
RING_SLOTS = 8
SLOT_FIELDS = 11
FIELDS = ("seq", "rep", "pose", "ball", "touch", "trig", "x", "y", "z", "r1", "r2")
MISS_TOL_MM = 0.001  # a latch this close to the commanded end point counts as "not triggered"
_SAFE_TEXT = re.compile(r"\A[A-Za-z0-9 _.,:=+\-]*\Z")  # fullmatch: "$" lets a final "\n" by
_NUM = r"[+-]?(?:\d+\.?\d*|\.\d+)"
VERDICT_CODES = (1, 2, 3, 4)  # drivers.base.VERDICT_CODES without "none yet" (0)
# re.ASCII: without it \d and \s also match '٣' or a no-break space, which no control prints
_LINE = re.compile(
    rf"^\s*RUMBA\s+(?P<seq>\d+)\s+(?P<rep>\d+)\s+(?P<pose>\d+)\s+(?P<ball>[A-Za-z0-9_.-]{{1,32}})"
    rf"\s+(?P<touch>[1-5])\s+(?P<trig>{_NUM})\s+(?P<x>{_NUM})\s+(?P<y>{_NUM})\s+(?P<z>{_NUM})"
    rf"\s+(?P<r1>{_NUM})\s+(?P<r2>{_NUM})\s*$", re.ASCII)
# Plausibility of a latched value (drivers.hits has the same ceilings for the record links): a
# result beyond them is a garbled line, journaling it would only move the failure to analysis.
MAX_RESULT_MM = 1e5
MAX_RESULT_DEG = 1e5


def safe_text(s: str) -> str:
    """Refuse any string that could break out of a comment or a message (only ``[A-Za-z0-9
    _.,:=+-]`` reach a program)."""
    if not isinstance(s, str) or not _SAFE_TEXT.fullmatch(s):
        bad = sorted({ch for ch in str(s) if not _SAFE_TEXT.fullmatch(ch)})
        raise ProgramError(f"text {s!r} contains {bad}: not allowed in a program")
    return s


class Code(str):
    """A program fragment built by a dialect class from constants, axis letters and formatted
    numbers (never from a configuration string): printed as is."""


def _finalize(v: object) -> object:
    """Every ``{{ … }}`` output: plain strings are sanitised (they may come from configuration),
    ``Code`` passes, floats must have been formatted."""
    if isinstance(v, bool | float):
        raise ProgramError(f"template printed a raw {type(v).__name__} {v!r}: format it")
    if isinstance(v, Code):
        return v
    if isinstance(v, str):
        return safe_text(v)
    return v


def _env() -> jinja2.Environment:
    env = jinja2.Environment(
        loader=jinja2.FileSystemLoader(str(TEMPLATES)), undefined=jinja2.StrictUndefined,
        autoescape=False, trim_blocks=True, lstrip_blocks=True, keep_trailing_newline=True,
        finalize=_finalize)
    return env


def fmt(v: float) -> str:
    s = f"{v:.4f}"
    return "0.0000" if s == "-0.0000" else s


def sfmt(v: float) -> str:
    s = f"{v:+.4f}"
    return "+0.0000" if s == "-0.0000" else s


@dataclass(frozen=True)
class Block:
    """What a template sees for one move (strings already formatted and sanitised)."""

    n: int
    kind: str  # rapid | linear | probe | dwell
    words: str
    feed: str
    dwell: str
    comment: str
    touch: dict | None


class Dialect:
    """Base class: subclasses set the constants and the latched-value sources."""

    name = ""
    extension = ""
    counter = ""
    slot_prefix = ""
    slot_base = 0
    result_line = "RUMBA <seq> <rep> <pose> <ball> <touch> <trig> <x> <y> <z> <r1> <r2>"
    result_channel = ""  # where the controller writes the result lines
    verdict_variable = ""  # where the verdict program writes the verdict code (1-4)

    def __init__(self) -> None:
        self._template = _env().get_template(f"{self.name}/program.j2")

    # ---------------------------------------------------------------- capture
    def slot_address(self, seq: int, field: int | str) -> str:
        """Variable holding ``field`` (index or name in FIELDS) of touch ``seq``'s slot."""
        f = FIELDS.index(field) if isinstance(field, str) else int(field)
        return Code(f"{self.slot_prefix}"
                    f"{self.slot_base + SLOT_FIELDS * ((seq - 1) % RING_SLOTS) + f}")

    def parse_result(self, line: str) -> ProbeHit | None:
        """Decode one result line; None for other output; ValueError for a broken RUMBA line."""
        if not line.lstrip().startswith("RUMBA"):
            return None
        m = _LINE.fullmatch(line.rstrip("\r\n"))
        if not m:
            raise ValueError(f"result line does not match the grammar "
                             f"'RUMBA seq rep pose ball touch trig x y z r1 r2': {line.strip()!r}")
        g = m.groupdict()
        touch = int(g["touch"])
        r1, r2 = float(g["r1"]), float(g["r2"])
        trig = float(g["trig"])
        if trig not in (0.0, 1.0):
            raise ValueError(f"result line: trigger flag {g['trig']} is neither 0 nor 1: "
                             f"{line.strip()!r}")
        for key, limit, unit in (("x", MAX_RESULT_MM, "mm"), ("y", MAX_RESULT_MM, "mm"),
                                 ("z", MAX_RESULT_MM, "mm"), ("r1", MAX_RESULT_DEG, "deg"),
                                 ("r2", MAX_RESULT_DEG, "deg")):
            value = float(g[key])
            if not math.isfinite(value) or abs(value) > limit:
                raise ValueError(f"result line: {key} = {g[key][:24]} {unit} is beyond "
                                 f"±{limit:g} {unit}: {line.strip()[:120]!r}")
        # Unbound: rotary values under the log's column names b / c (BoundDialect uses letters).
        return ProbeHit(seq=int(g["seq"]), pose=int(g["pose"]), ball=g["ball"], touch=touch,
                        axes={"X": float(g["x"]), "Y": float(g["y"]), "Z": float(g["z"]),
                              "b": r1, "c": r2},
                        triggered=trig == 1.0, repeat=int(g["rep"]), raw=line.strip(),
                        b_cmd_deg=r1, c_cmd_deg=r2, direction=TOUCH_DIRECTIONS[touch])

    def bind(self, program: Program) -> BoundDialect:
        """A parser that knows the program: rotary letters, commanded values, identity check."""
        return BoundDialect(self, program)

    # ---------------------------------------------------------------- verdict
    def verdict_program(self, code: int) -> str:
        """A tiny program setting ``verdict_variable`` to ``code`` (1-4; nothing else reaches
        it, so nothing can be injected), LF line ends, for DNC drip-feeding."""
        if type(code) is not int or code not in VERDICT_CODES:  # a bool is not a code
            raise ProgramError(f"verdict code {code!r}: expected one of {VERDICT_CODES}")
        return "\n".join(self._verdict_lines(code)) + "\n"

    def _verdict_lines(self, code: int) -> list[str]:
        raise NotImplementedError

    # ---------------------------------------------------------------- rendering
    def sources(self, program: Program) -> list[str]:
        """Expressions of fields 5..10 (trig, X, Y, Z, r1, r2) right after a probing move."""
        raise NotImplementedError

    def words(self, letters: Sequence[str], values: Sequence[float]) -> str:
        return Code(" ".join(f"{a}{fmt(v)}" for a, v in zip(letters, values, strict=True)))

    def check_ball_id(self, ball: str) -> None:
        # a ball id is a word of the result line and part of file names: a safe name, not text
        if not isinstance(ball, str) or not SAFE_NAME.fullmatch(ball):
            raise ProgramError(f"ball id {ball!r} is not a safe name (letters, digits, '_', "
                               "'.', '-', 1-32 characters)")

    def touch_context(self, program: Program, t: Touch) -> dict:
        letters = program.axis_letters
        seq = t.id.seq
        self.check_ball_id(t.id.ball)  # printed in result lines, messages and file names
        consts = [t.id.seq, t.id.repeat, t.id.pose, t.ball_number, t.id.touch]
        ctx = {
            "seq": seq, "rep": t.id.repeat, "pose": t.id.pose, "ball": t.id.ball,
            "ball_no": t.ball_number, "touch": t.id.touch,
            "slot": [(self.slot_address(seq, f), str(v)) for f, v in enumerate(consts)],
            "latched": [(self.slot_address(seq, 5 + i), Code(src))
                        for i, src in enumerate(self.sources(program))],
            "trig_var": self.slot_address(seq, 5),
            "value_vars": [self.slot_address(seq, 6 + i) for i in range(5)],
            "end": [fmt(v) for v in t.end], "send": [sfmt(v) for v in t.end],
            # A TNC probing cycle rapids (FMAX) to the point it is given, then probes along its
            # direction for DIST of the touch-probe table: it must get the start point.
            "sstart": [sfmt(v) for v in t.start],
            "r1": letters[3], "r2": letters[4],
        }
        return ctx

    def blocks(self, program: Program) -> list[Block]:
        out = []
        letters = program.axis_letters
        for b in program.artefact.balls:
            self.check_ball_id(b.id)
        last_pose = -2
        for mv in program.moves:
            comment = ""
            if mv.kind == "rapid" and set(mv.words) & set(letters[3:]) and mv.pose != last_pose:
                p = program.plan.poses[mv.pose]
                comment = f"POSE {mv.pose} {letters[3]} {p.b_deg:g} {letters[4]} {p.c_deg:g}"
                last_pose = mv.pose
            touch = None
            if mv.kind == "probe" and mv.touch is not None:
                t = mv.touch
                touch = self.touch_context(program, t)
                comment = (f"SEQ {t.id.seq} REP {t.id.repeat} POSE {t.id.pose} BALL {t.id.ball}"
                           f" TOUCH {t.id.touch}")
            idx = [letters.index(w) for w in mv.words]
            kind = {"retract": "linear" if mv.feed_mm_min else "rapid",
                    "feed": "linear"}.get(mv.kind, mv.kind)
            out.append(Block(mv.block, kind, self.words(mv.words, [mv.target[i] for i in idx]),
                             fmt(mv.feed_mm_min), f"{mv.dwell_s:.3f}", safe_text(comment),
                             touch))
        return out

    def context(self, program: Program) -> dict:
        plan = program.plan
        for what, name in (("plan", plan.name), ("machine", program.machine.name),
                           ("artefact", program.artefact.name)):
            if not isinstance(name, str) or not SAFE_NAME.fullmatch(name):  # a bypass
                raise ProgramError(f"{what} name {name!r} is not a safe name: not allowed in a "
                                   "program")
        info = [f"PLAN {plan.name}", f"MACHINE {program.machine.name}",
                f"ARTEFACT {program.artefact.name}", f"TOUCHES {len(program.touches)}",
                f"TARGETS {program.targets.source}",
                f"STANDOFF {program.standoff_mm:g} OVERTRAVEL {program.overtravel_mm:g}",
                f"STYLUS DIAMETER {plan.stylus_diameter_mm:g}",
                f"CYCLE TIME {estimate(program).summary().replace('(', '').replace(')', '')}"]
        return {"title": "RUMBA PROBING PROGRAM", "info": [safe_text(x) for x in info],
                "blocks": self.blocks(program), "counter": Code(self.counter),
                "miss_tol": fmt(MISS_TOL_MM), "r1": program.rotary[0], "r2": program.rotary[1]}

    def render(self, program: Program) -> str:
        """The program text (LF line ends; transports convert)."""
        return self._template.render(**self.context(program))

    def aux_files(self, program: Program) -> dict[str, str]:
        """Extra files a controller needs next to the program (Heidenhain format files)."""
        return {}


class Fanuc(Dialect):
    """Fanuc 0i/30i macro B (also Haas): G31, #5061-#5065, DPRNT, #3000 alarm."""

    name, extension, counter, slot_prefix, slot_base = "fanuc", "nc", "#599", "#", 600
    result_channel = "DPRNT on the DNC serial port (POPEN/PCLOS)"
    verdict_variable = "#598"  # common variable, retained (#500-#999), next to the ring
    verdict_program_number = 9101

    def _verdict_lines(self, code: int) -> list[str]:
        return ["%", f"O{self.verdict_program_number} (RUMBA VERDICT)",
                f"{self.verdict_variable}={code}.", "M30", "%"]

    def __init__(self, haas: bool = False) -> None:
        super().__init__()
        self.haas = haas

    def check_ball_id(self, ball: str) -> None:
        if not re.fullmatch(r"[A-Z0-9]{1,12}", ball):
            raise ProgramError(f"ball id {ball!r}: the fanuc dialect needs [A-Z0-9]{{1,12}} "
                               "(Fanuc program text and DPRNT have no lower case or '_')")

    def sources(self, program: Program) -> list[str]:
        if self.haas:
            rot = [f"#{5061 + 'XYZABC'.index(a)}" for a in program.rotary]
        else:
            rot = ["#5064", "#5065"]  # 4th and 5th axis = first and second rotary letter
        return ["1.", "#5061", "#5062", "#5063", *rot]

    program_number = 9100

    def context(self, program: Program) -> dict:
        ctx = super().context(program)
        ctx["info"] = [x.upper() for x in ctx["info"]]
        return {**ctx, "program_number": self.program_number}


class LinuxCNC(Dialect):
    """LinuxCNC 2.9: G38.2, #5061-#5070, (LOG,…), O-word miss check guarded by #<_task>."""

    name, extension, counter, slot_prefix, slot_base = "linuxcnc", "ngc", "#3999", "#", 4000
    log_file = "rumba_results.log"
    result_channel = f"(LOG,…) lines in {log_file} (LinuxCNC's working directory)"
    verdict_variable = "#3998"  # user numbered parameter (#31-#5000), next to the ring

    def _verdict_lines(self, code: int) -> list[str]:
        return ["%", "(RUMBA VERDICT)", f"{self.verdict_variable} = {code}", "M2", "%"]

    def sources(self, program: Program) -> list[str]:
        rot = [f"#{5061 + 'XYZABC'.index(a)}" for a in program.rotary]
        return ["#5070", "#5061", "#5062", "#5063", *rot]

    def context(self, program: Program) -> dict:
        return {**super().context(program), "log_file": self.log_file}


class Siemens(Dialect):
    """Sinumerik 840D: MEAS=1 G1, $AA_MW / $AC_MEA, R parameters, WRITE, SETAL."""

    name, extension, counter, slot_prefix, slot_base = "siemens", "mpf", "R99", "R", 100
    result_channel = "WRITE to the file RUMBA_RES (part-program memory)"
    verdict_variable = "R4"  # the OPC UA map's verdict node /Channel/Parameter/R[u1,4]

    def _verdict_lines(self, code: int) -> list[str]:
        return ["; RUMBA VERDICT", f"{self.verdict_variable}={code}", "M30"]

    def sources(self, program: Program) -> list[str]:
        return ["$AC_MEA[1]", "$AA_MW[X]", "$AA_MW[Y]", "$AA_MW[Z]",
                *(f"$AA_IW[{a}]" for a in program.rotary)]


class Heidenhain(Dialect):
    """Heidenhain TNC conversational: TCH PROBE 0/1, Q115-Q119, FN 16 F-PRINT, FN 14 ERROR."""

    name, extension, counter, slot_prefix, slot_base = "heidenhain", "h", "Q1599", "Q", 1600
    result_channel = "FN 16 F-PRINT to RUMBA_RES.TXT next to the program"
    print_base = 1580
    verdict_variable = "Q1598"  # next to the ring counter Q1599

    def _verdict_lines(self, code: int) -> list[str]:
        return ["0 BEGIN PGM RUMBAV MM", f"1 {self.verdict_variable} = +{code}",
                "2 END PGM RUMBAV MM"]

    def sources(self, program: Program) -> list[str]:
        return ["TRIG", "Q115", "Q116", "Q117", "Q118", "Q119"]

    def words(self, letters: Sequence[str], values: Sequence[float]) -> str:
        return Code(" ".join(f"{a}{sfmt(v)}" for a, v in zip(letters, values, strict=True)))

    def touch_context(self, program: Program, t: Touch) -> dict:
        ctx = super().touch_context(program, t)
        d = [e - s for e, s in zip(t.end, t.start, strict=True)]
        n = math.sqrt(sum(x * x for x in d))
        u = [x / n for x in d]
        if abs(u[2]) < 1e-9:
            ctx["cycle"] = 1
            ctx["angle"] = sfmt(math.degrees(math.atan2(u[1], u[0])) % 360.0)
        else:
            k = max(range(3), key=lambda i: abs(u[i]))
            if abs(abs(u[k]) - 1.0) > 1e-9:
                raise ProgramError(f"touch seq {t.id.seq}: heidenhain cycles probe in the X-Y "
                                   "plane or along one axis only")
            ctx["cycle"] = 0
            ctx["axis"] = "XYZ"[k] + ("+" if u[k] > 0 else "-")
        ctx["print"] = [Code(f"Q{self.print_base + f}") for f in range(SLOT_FIELDS)]
        ctx["format_file"] = Code(f"RUMBA_{t.id.ball}.A")  # checked by touch_context
        return ctx

    def render(self, program: Program) -> str:
        text = super().render(program)
        lines = text.rstrip("\n").split("\n")
        return "\n".join(f"{i} {line}" for i, line in enumerate(lines)) + "\n"

    def aux_files(self, program: Program) -> dict[str, str]:
        out = {}
        q = [f"Q{self.print_base + f}" for f in range(SLOT_FIELDS) if f != 3]
        for b in program.artefact.balls:
            self.check_ball_id(b.id)  # inside a quoted format string and a file name
            fmt_ = ("RUMBA %.0LF %.0LF %.0LF " + b.id
                    + " %.0LF %.0LF %.4LF %.4LF %.4LF %.4LF %.4LF\\n")
            out[f"RUMBA_{b.id}.A"] = f'"{fmt_}", ' + ", ".join(q) + ";\n"
        return out


DIALECTS: dict[str, type[Dialect]] = {"fanuc": Fanuc, "siemens": Siemens,
                                      "heidenhain": Heidenhain, "linuxcnc": LinuxCNC}


def get_dialect(name: str) -> Dialect:
    """A dialect by name (``haas`` is the fanuc dialect reading rotary skips by letter)."""
    if name == "haas":
        return Fanuc(haas=True)
    if name not in DIALECTS:
        raise ProgramError(f"unknown dialect {name!r} (known: {', '.join(sorted(DIALECTS))}, haas)")
    return DIALECTS[name]()


class BoundDialect:
    """``parse_result`` for one program: real rotary letters, commanded pose and direction, and a
    check that the line's identity is the program's touch of that seq (no guessing)."""

    def __init__(self, dialect: Dialect, program: Program) -> None:
        self.dialect = dialect
        self.rotary = program.rotary
        self.touches = {t.id.seq: t for t in program.touches}
        self.name = dialect.name

    def parse_result(self, line: str) -> ProbeHit | None:
        hit = self.dialect.parse_result(line)
        if hit is None:
            return None
        t = self.touches.get(hit.seq)
        if t is None:
            raise ValueError(f"result seq {hit.seq} is not a touch of this program")
        if (hit.pose, hit.ball, hit.touch, hit.repeat) != (t.id.pose, t.id.ball, t.id.touch,
                                                           t.id.repeat):
            raise ValueError(f"result seq {hit.seq} says pose {hit.pose} ball {hit.ball} touch "
                             f"{hit.touch} rep {hit.repeat}, the program has pose {t.id.pose} "
                             f"ball {t.id.ball} touch {t.id.touch} rep {t.id.repeat}")
        axes = {"X": hit.axes["X"], "Y": hit.axes["Y"], "Z": hit.axes["Z"],
                self.rotary[0]: hit.axes["b"], self.rotary[1]: hit.axes["c"]}
        return replace(hit, axes=axes, b_cmd_deg=t.b_deg, c_cmd_deg=t.c_deg,
                       direction=t.direction, feed_mm_min=t.feed_mm_min)


__all__ = ["DIALECTS", "Block", "BoundDialect", "Dialect", "Fanuc", "Heidenhain", "LinuxCNC",
           "Move", "Siemens", "get_dialect", "safe_text"]
