"""What every controller dialect shares: template rendering, result slots, result parsing."""

from __future__ import annotations

import dataclasses
import functools
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import jinja2
import numpy as np

from contracts.dialects import dialect as dialect_record
from contracts.jobs import VERDICT_CODES
from contracts.messages import ProbeHit
from contracts.result_lines import (
    RESULT_FIELDS,
    RING_SLOTS,
    SLOT_FIELDS,
    parse_result_line,
)
from contracts.setup_files import SAFE_NAME
from programs.cycletime import CycleTime, estimate
from programs.geometry import ProgramError
from programs.model import Program, Touch

TEMPLATES = Path(__file__).resolve().parents[2] / "gcode_templates"
MISS_TOL_MM = 0.001  # a latch this close to the commanded end point counts as "not triggered"
_BLOCK_NUMBER = re.compile(r"\AN?[0-9]+\s+")  # "N120 " (ISO), "49 " (Heidenhain)
_SAFE_TEXT = re.compile(r"\A[A-Za-z0-9 _.,:=+\-]*\Z")  # fullmatch: "$" lets a final "\n" by
_VERDICTS = tuple(VERDICT_CODES.values())  # the codes a verdict program may write (not 0)


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


@functools.cache
def _env() -> jinja2.Environment:
    """The templates' one environment: each template is compiled to Python once per process,
    not for every program (a dialect object per run, per plan candidate)."""
    return jinja2.Environment(
        loader=jinja2.FileSystemLoader(str(TEMPLATES)), undefined=jinja2.StrictUndefined,
        autoescape=False, trim_blocks=True, lstrip_blocks=True, keep_trailing_newline=True,
        finalize=_finalize)


def fmt(v: float) -> str:
    """A coordinate as the programs print it (4 decimals, never ``-0.0000``)."""
    s = f"{v:.4f}"
    return "0.0000" if s == "-0.0000" else s


def sfmt(v: float) -> str:
    """A coordinate with its sign always printed (Heidenhain)."""
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
    # two-speed probe (dialects with ``two_speed``): the locating feed, the back-off words
    # relative to the latched point and their feed; "" for a one-speed probe
    locate_feed: str = ""
    backoff: str = ""
    backoff_feed: str = ""
    pose_start: int | None = None  # the first block of this plan pose (temperature prints)
    last_touch: bool = False  # the program's last probing block (its end temperatures)


class Dialect:
    """Base class: subclasses set the constants and the latched-value sources.

    Result slots (variable capture, contracts.result_lines): per touch the program writes slot
    ``(seq-1) % RING_SLOTS`` with the ``RESULT_FIELDS`` (ball as its 1-based number), then the
    counter = seq; addresses: ``counter`` and ``slot_address(seq, field)``. Verdict write-back
    by program (serial DNC): ``verdict_program(code)`` sets ``verdict_variable`` to the code;
    the CNC's start-of-shift macro clears it before printing ``RUMBA REQUEST <machine>`` and
    waits for it to become non-zero. Every construct each dialect emits is listed in
    gcode_templates/<dialect>/README.md."""

    name = ""
    record_name = ""  # the dialect record that made it (``get_dialect``), when not ``name``
    extension = ""
    counter = ""
    slot_prefix = ""
    slot_base = 0
    result_channel = ""  # where the controller writes the result lines
    verdict_variable = ""  # where the verdict program writes the verdict code (1-4)
    two_speed = False  # can render a two-speed touch (``backoff_words``)
    # A tilted-probe program commands the head pivot through X Y Z: the control's
    # tool-centre-point transformation must be off; ``tcpm_off`` is the block that ensures it
    # (a safety precondition, after the modal line), ``tcpm_note`` what the header says.
    tcpm_off = ""
    tcpm_note = ""
    # Is a multi-axis rapid a straight line on this control? Then the checked
    # straight transits of a tilted-probe program (``Move.linear_rapid``) run as rapids, after
    # ``linear_rapid_on`` (the block that makes it so, if the control has one); else they stay
    # linear moves at the max feed — a non-linear rapid would leave the checked line.
    linear_rapid = False
    linear_rapid_on = ""
    # The line whose execution prints a touch's result line (after the counter = seq line of
    # that touch); ``result_armed`` (siemens: the RLINE assignment) must precede it when the
    # print line itself does not say it is a result: ``last_printed_seq``.
    result_print: re.Pattern[str] = re.compile(r"(?!)")
    result_armed: re.Pattern[str] | None = None

    def __init__(self) -> None:
        self._template = _env().get_template(f"{self.name}/program.j2")

    @property
    def label(self) -> str:
        """The dialect as the user named it (``--dialect``, daemon.yaml): what the program's
        header and the command's summary say; ``name`` is the template family."""
        return self.record_name or self.name

    # ---------------------------------------------------------------- capture
    def slot_address(self, seq: int, field: int | str) -> str:
        """Variable holding ``field`` (index or name in RESULT_FIELDS) of touch ``seq``'s slot."""
        f = RESULT_FIELDS.index(field) if isinstance(field, str) else int(field)
        return Code(f"{self.slot_prefix}"
                    f"{self.slot_base + SLOT_FIELDS * ((seq - 1) % RING_SLOTS) + f}")

    def parse_result(self, line: str) -> ProbeHit | None:
        """Decode one result line; None for other output; ValueError for a broken RUMBA line."""
        return parse_result_line(line)

    def last_printed_seq(self, text: str) -> int:
        """The seq of the last touch whose result line ``text`` (a part of this dialect's
        program: the bytes a DNC link fed before it stopped) prints, 0 if none: the most a
        control that received it can still print (serial DNC after an abort)."""
        counter = re.compile(rf"{re.escape(self.counter)}\s*=\s*\+?([0-9]+)\.?")
        seq, last, armed = 0, 0, self.result_armed is None
        for raw in text.splitlines():
            line = _BLOCK_NUMBER.sub("", raw.strip())
            if m := counter.fullmatch(line):
                seq = int(m.group(1))
            if self.result_armed is not None and line.startswith(("RLINE=", "RLINE =")):
                armed = bool(self.result_armed.match(line))
            if armed and self.result_print.match(line):
                last = seq
        return last

    def bind(self, program: Program) -> BoundDialect:
        """A parser that knows the program: rotary letters, commanded values, identity check."""
        return BoundDialect(self, program)

    # ---------------------------------------------------------------- verdict
    def verdict_program(self, code: int) -> str:
        """A tiny program setting ``verdict_variable`` to ``code`` (1-4; nothing else reaches
        it, so nothing can be injected), LF line ends, for DNC drip-feeding."""
        if type(code) is not int or code not in _VERDICTS:  # a bool is not a code
            raise ProgramError(f"verdict code {code!r}: expected one of {_VERDICTS}")
        return "\n".join(self._verdict_lines(code)) + "\n"

    def _verdict_lines(self, code: int) -> list[str]:
        raise NotImplementedError

    # ---------------------------------------------------------------- rendering
    def sources(self, program: Program) -> list[str]:
        """Expressions of fields 5..10 (trig, X, Y, Z, r1, r2) right after a probing move."""
        raise NotImplementedError

    def words(self, letters: Sequence[str], values: Sequence[float]) -> str:
        """The axis words of one block."""
        return Code(" ".join(f"{a}{fmt(v)}" for a, v in zip(letters, values, strict=True)))

    def check_ball_id(self, ball: str) -> None:
        """Refuse a ball id the dialect cannot print."""
        # a ball id is a word of the result line and part of file names: a safe name, not text
        if not isinstance(ball, str) or not SAFE_NAME.fullmatch(ball):
            raise ProgramError(f"ball id {ball!r} is not a safe name (letters, digits, '_', "
                               "'.', '-', 1-32 characters)")

    def touch_context(self, program: Program, t: Touch) -> dict:
        """What a template sees of one touch's probing block."""
        letters = program.axis_letters
        seq = t.id.seq
        self.check_ball_id(t.id.ball)  # printed in result lines, messages and file names
        consts = [t.id.seq, t.id.repeat, t.id.pose, t.ball_number, t.id.touch]
        return {
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

    def blocks(self, program: Program) -> list[Block]:
        """Every move of the program as a template block."""
        out = []
        letters = program.axis_letters
        for b in program.artefact.balls:
            self.check_ball_id(b.id)
        last_pose = -2
        prev_pose = -1
        for mv in program.moves:
            start = mv.pose if mv.pose >= 0 and mv.pose != prev_pose else None
            prev_pose = mv.pose if mv.pose >= 0 else prev_pose
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
            rapid = mv.linear_rapid and self.linear_rapid  # a checked straight line
            kind = {"retract": "linear" if mv.feed_mm_min and not rapid else "rapid",
                    "feed": "rapid" if rapid else "linear"}.get(mv.kind, mv.kind)
            two = {}
            if mv.kind == "probe" and mv.locate_feed_mm_min > 0 and mv.touch is not None:
                if not self.two_speed:
                    raise ProgramError(f"the {self.name} dialect has no two-speed touch: build "
                                       "the program with two_speed=False (programs.generate)")
                u = np.array(mv.touch.end) - np.array(mv.touch.start)
                back = -mv.backoff_mm * u / np.linalg.norm(u)
                two = {"locate_feed": fmt(mv.locate_feed_mm_min),
                       "backoff": self.backoff_words(back),
                       "backoff_feed": fmt(program.plan.feeds.approach_mm_min)}
            out.append(Block(mv.block, kind, self.words(mv.words, [mv.target[i] for i in idx]),
                             fmt(mv.feed_mm_min), f"{mv.dwell_s:.3f}", safe_text(comment),
                             touch, **two, pose_start=start))
        last = max((i for i, b in enumerate(out) if b.touch is not None), default=None)
        if last is not None:  # printed before the last result line: the link has them when
            out[last] = dataclasses.replace(out[last], last_touch=True)  # its run ends
        return out

    def temperature_prints(self, program: Program) -> list[dict]:
        """The macro variables the program prints, each checked against the
        dialect's variable form (contracts.dialects: ``temperature_variable``): nothing else
        reaches the program text."""
        if not program.temperature_vars:
            return []
        rec = dialect_record(self.label)
        if rec.temperature_variable is None:
            raise ProgramError(f"the {self.name} dialect prints no temperature lines; read "
                               "the channels through a transmitter")
        out = []
        for k, var in enumerate(program.temperature_vars, 1):
            if not isinstance(var, str) or not rec.prints_temperature(var):
                raise ProgramError(f"temperature variable {var!r} is not a {self.name} "
                                   "variable the program may print")
            out.append({"k": k, "var": Code(var)})
        return out

    def backoff_words(self, offset_mm: np.ndarray) -> str:
        """X Y Z words moving to the last latched point + ``offset_mm`` (two-speed touch)."""
        raise NotImplementedError

    def context(self, program: Program, cycle_time: CycleTime) -> dict:
        """Everything the program template sees."""
        plan = program.plan
        for what, name in (("plan", plan.name), ("machine", program.machine.name),
                           ("artefact", program.artefact.name)):
            if not isinstance(name, str) or not SAFE_NAME.fullmatch(name):  # a bypass
                raise ProgramError(f"{what} name {name!r} is not a safe name: not allowed in a "
                                   "program")
        info = [f"DIALECT {self.label}", f"PLAN {plan.name}",
                f"MACHINE {program.machine.name}", f"ARTEFACT {program.artefact.name}",
                f"TOUCHES {len(program.touches)}", f"TARGETS {program.targets.source}",
                f"STANDOFF {program.standoff_mm:g} OVERTRAVEL {program.overtravel_mm:g}",
                f"STYLUS DIAMETER {plan.stylus_diameter_mm:g}",
                f"CYCLE TIME {cycle_time.summary().replace('(', '').replace(')', '')}"]
        if program.tilted:
            info += [f"TILTED PROBE: {self.tcpm_note}",
                     "X Y Z COMMAND THE HEAD PIVOT: NO TOOL LENGTH OFFSET, NO TILTED PLANE"]
        return {"title": "RUMBA PROBING PROGRAM", "info": [safe_text(x) for x in info],
                "tcpm_off": Code(self.tcpm_off) if program.tilted else "",
                "linear_rapid_on": Code(self.linear_rapid_on) if self.linear_rapid and any(
                    mv.linear_rapid for mv in program.moves) else "",
                "blocks": self.blocks(program), "counter": Code(self.counter),
                "temperatures": self.temperature_prints(program),
                "miss_tol": fmt(MISS_TOL_MM), "r1": program.rotary[0], "r2": program.rotary[1],
                "handshake": self.handshake(program)}

    def handshake(self, program: Program) -> dict | None:
        """The ring wait and stop check (``Program.handshake``): the variables the link writes,
        or None; a dialect without them refuses (its links read no variables)."""
        if not program.handshake:
            return None
        rec = dialect_record(self.label)
        stop = rec.stop_program
        if stop is not None:  # the link writes files, not variables: a called stop program
            return {"stop_program": Code(stop[0]), "stop": Code(stop[1])}
        pair = rec.handshake_variables
        if pair is None:
            raise ProgramError(f"the {self.label} dialect has no result handshake: its links "
                               "read the results another way")
        return {"ack": Code(pair[0]), "stop": Code(pair[1]), "slots": RING_SLOTS}

    def render(self, program: Program, cycle_time: CycleTime | None = None) -> str:
        """The program text (LF line ends; transports convert); ``cycle_time``: the program's
        estimate when the caller has it (``programs.generate``), else computed here."""
        ct = cycle_time if cycle_time is not None else estimate(program, self.linear_rapid)
        return self._template.render(**self.context(program, ct))

    def aux_files(self, program: Program) -> dict[str, str]:
        """Extra files a controller needs next to the program (Heidenhain format files)."""
        return {}


class BoundDialect:
    """``parse_result`` for one program: real rotary letters, and identity check and commanded
    pose, direction and feed from the program's touch table (no guessing)."""

    def __init__(self, dialect: Dialect, program: Program) -> None:
        self.dialect = dialect
        self.rotary = program.rotary
        self.table = program.touch_table()
        self.name = dialect.name

    def last_printed_seq(self, text: str) -> int:
        return self.dialect.last_printed_seq(text)

    def parse_result(self, line: str) -> ProbeHit | None:
        """Decode one result line and complete it from the program; ValueError when broken or
        not this program's touch."""
        hit = self.dialect.parse_result(line)
        if hit is None:
            return None
        why = self.table.mismatch(hit)
        if why:
            raise ValueError(why)
        axes = {"X": hit.axes["X"], "Y": hit.axes["Y"], "Z": hit.axes["Z"],
                self.rotary[0]: hit.axes["b"], self.rotary[1]: hit.axes["c"]}
        return self.table.complete(hit, axes=axes)
