"""Property-based fuzzing of the other input surfaces read from the command line and
files: who confirms a compensation (``--by``, HMI names), control characters in a centres file
or a log, the plan name, ``rumba plan -o`` and ``--max-time``, ``rumba gcode`` on a spindle axis
that is no direction (the network ones: tests/test_inputs_fuzz_network.py). Classified and
counted as in tests/test_inputs_fuzz.py (``benchmarks.rigs.input_fuzz_helpers``);
``benchmarks/fuzz/inputs.py`` runs the same tests longer."""

from __future__ import annotations

import contextlib
import copy
import io
import math
import re
import unicodedata
from pathlib import Path

import numpy as np
import yaml
from hypothesis import given
from hypothesis import strategies as st

from benchmarks.rigs.input_fuzz_helpers import Tally, outcome
from benchmarks.rigs.reader_helpers import CONFIG
from contracts.plan_targets import load_targets_file
from contracts.yaml_files import ConfigError
from daemon.compensation.names import BadName, validate_by
from tests.test_inputs_fuzz import FUZZ

# ----------------------------------------------------------------------------- --by, HMI

_CONFUSABLE = {"u": "υսμцｕ", "n": "ոηпｎ", "a": "аɑαａ", "t": "τтţｔ", "e": "еεҽｅ",
               "d": "ԁďｄ"}


def _printable(name: str) -> bool:
    """The journal's rule, stated on its own: 1-64 characters of printable text on one line,
    no control, format or separator character but the plain space, no outer spaces."""
    return (0 < len(name) <= 64 and name == name.strip()
            and not any(unicodedata.category(c)[0] == "C"
                        or (unicodedata.category(c)[0] == "Z" and c != " ") for c in name))


def _reads_as_marker(name: str) -> bool:
    """Its letters, marks dropped and compatibility forms folded, spell the marker."""
    letters = unicodedata.normalize("NFKD", unicodedata.normalize("NFKC", name).casefold())
    return "".join(c for c in letters if c.isalpha() and not unicodedata.combining(c)) \
        == "unattended"


def _by(name: str, allow: bool) -> str:
    try:
        return validate_by(name, "--by", allow_unattended=allow)
    except BadName as e:  # one line naming the option, as `rumba compensate` prints it
        raise ConfigError(str(e)) from None


@st.composite
def _lookalike(draw: st.DrawFn) -> str:
    """``unattended`` disguised: cases changed, letters swapped for another script's or a
    full-width form, separators and combining marks added."""
    out = []
    for ch in "unattended":
        how = draw(st.sampled_from(["same", "upper", "confusable", "sep", "mark"]))
        if how == "upper":
            ch = ch.upper()
        elif how == "confusable":
            ch = draw(st.sampled_from(_CONFUSABLE[ch]))
        elif how == "sep":
            ch += draw(st.sampled_from(["-", "_", ".", " ", "·"]))
        elif how == "mark":
            ch += draw(st.sampled_from(["\u0301", "\u0308", "\u0327"]))
        out.append(ch)
    name = "".join(out).strip()
    return name if name != "unattended" else name.upper()


_NAMES = st.one_of(
    st.text(max_size=80),
    st.text(st.characters(codec="utf-8", exclude_categories=("Cs",)), min_size=1, max_size=70),
    st.sampled_from(["alice", "Jürgen Müller", "王小明", "shift-2 (night)", "unattended",
                     "alice\nrun 7 applied by bob", "\x1b[31mroot\x1b[0m", "bob\u202eecila",
                     "\u200bunattended", "x" * 65, "x" * 64, " alice", "alice ", "a\u00a0b",
                     "a\u2028b", "a\tb", "\ufeffalice", "unattended\u0000"]),
    st.builds(lambda n, k: n * k, st.sampled_from(["a", "é", "中", "\n"]),
              st.sampled_from([1, 63, 64, 65, 1 << 20])))


def test_who_confirms_is_printable_and_never_the_marker() -> None:
    tally = Tally("--by / HMI names")

    @FUZZ
    @given(name=st.one_of(_NAMES, _lookalike()), allow=st.booleans())
    def run(name: str, allow: bool) -> None:
        if name == "unattended":
            valid = allow
        elif _printable(name) and not _reads_as_marker(name):
            valid = True
        else:
            valid = False
        if valid and any(c in name for c in "".join(_CONFUSABLE.values())):
            valid = None  # other scripts' letters: refused only when they spell the marker
        tally.add(outcome(lambda: _by(name, allow), "--by", valid,
                          lambda out: out == name), (name[:80], allow))

    run()
    tally.verdict()


# ------------------------------------------------------- control characters, centres, log


def test_a_control_character_in_a_centres_file_or_log_is_never_accepted(tmp_path: Path
                                                                         ) -> None:
    """The centres CSV (``rumba-centres v1``: a comment, a header value, a cell) and the
    probing log — never read as if the character were not there (Python's strip() takes
    \\x0b, \\x0c, \\x1c-\\x1f away); tests/test_inputs_fuzz.py does KinOpt and DMIS."""
    from benchmarks.rigs.input_fuzz_helpers import EXAMPLE_LOG, READERS
    from benchmarks.rigs.reader_helpers import centre_rows
    from contracts.centres_file import read_centres, write_centres

    tally = Tally("centres/log control chars")
    base = tmp_path / "base.csv"
    write_centres(base, centre_rows(), instrument="CMM PMM-C 700", source="lab run 7",
                  comments=["provenance: ball bar check"])
    texts = {"centres": base.read_text().split("\n"), "log": EXAMPLE_LOG.read_text().split("\n")}
    control = [chr(c) for c in [*range(0, 9), 11, 12, *range(14, 32), 127]]

    @FUZZ
    @given(kind=st.sampled_from(["centres", "log"]), line=st.integers(0, 10_000),
           col=st.integers(0, 200), ch=st.sampled_from(control))
    def run(kind: str, line: int, col: int, ch: str) -> None:
        body = list(texts[kind])
        k = line % (len(body) - 1)  # not the empty string after the last newline
        c = col % (len(body[k]) + 1)
        body[k] = body[k][:c] + ch + body[k][c:]
        path = tmp_path / f"{kind}.csv"
        path.write_text("\n".join(body), encoding="utf-8")
        reader = read_centres if kind == "centres" else READERS["log"]
        tally.add(outcome(lambda: reader(path), path, False),
                  (kind, body[k][:60], c, hex(ord(ch))))

    run()
    tally.verdict()


# ----------------------------------------------------------------------- rumba plan inputs

_PLAN_NAMES = st.one_of(st.text(max_size=40),
                        st.from_regex(r"[A-Za-z0-9_.-]{1,34}", fullmatch=True),
                        st.sampled_from([".", "..", "...", "a/b", "../x", "x\x00", "x y",
                                         "ｘ", "-", "_", "a" * 32, "a" * 33, "shift.v2"]))


def test_a_plan_name_is_a_plain_file_name(tmp_path: Path) -> None:
    tally = Tally("plan names")
    target = yaml.safe_load((CONFIG / "plans/targets/shift_start.yaml").read_text())
    target["reference_plan"] = str(CONFIG / "plans/shift_start_14poses.yaml")

    @FUZZ
    @given(name=_PLAN_NAMES)
    def run(name: str) -> None:
        path = tmp_path / "targets.yaml"
        path.write_text(yaml.safe_dump({**target, "name": name}), encoding="utf-8")
        valid = bool(re.fullmatch(r"[A-Za-z0-9_.-]{1,32}", name, re.ASCII)) and \
            name.strip(".") != ""
        tally.add(outcome(lambda: load_targets_file(path), path, valid,
                          lambda t: t.name == name), name)

    run()
    tally.verdict()


_SECONDS = st.one_of(st.sampled_from(["90", "90.5", ".5", "0", "1.", "１", "٣", "1_0", "nan",
                                      "inf", "-1", "+1", "1e3", "", " 1", "1 ", "0x10",
                                      "9999999", "99999999", "1\x00", "²"]),
                     st.text("0123456789.-+e_ ", max_size=9), st.text(max_size=6))


def test_max_time_takes_plain_ascii_seconds() -> None:
    from daemon.cli.main import build_parser

    tally = Tally("plan --max-time")
    parser = build_parser()

    def parse(value: str) -> float:
        err = io.StringIO()
        try:
            with contextlib.redirect_stderr(err):
                args = parser.parse_args(["plan", "--machine", "m.yaml", "--artefact", "a.yaml",
                                          "--target", "t.yaml", f"--max-time={value}"])
        except SystemExit:
            lines = err.getvalue().strip().splitlines()
            raise ConfigError(f"--max-time: {lines[-1] if lines else ''}") from None
        return float(args.max_time)

    @FUZZ
    @given(value=_SECONDS)
    def run(value: str) -> None:
        plain = re.fullmatch(r"[0-9]+(\.[0-9]*)?|\.[0-9]+", value, re.ASCII)
        valid = None if plain and len(value.split(".")[0]) > 7 else bool(plain)
        tally.add(outcome(lambda: parse(value), "--max-time", valid,
                          lambda s: math.isfinite(s) and s == float(value)), value)

    run()
    tally.verdict()


def test_plan_output_is_never_written_through_a_link(tmp_path: Path) -> None:
    """``rumba plan -o``: the plan file itself, never a symbolic link (to a file, a directory
    or nowhere), never over an existing file without --force; a link's target untouched."""
    from daemon.cli.commands.plan import write_new
    from daemon.cli.main import UserError

    tally = Tally("plan -o")
    victim = tmp_path / "victim.txt"

    @FUZZ
    @given(kind=st.sampled_from(["new", "existing", "link-to-file", "dangling-link",
                                 "link-to-dir", "dir", "link-to-link"]), force=st.booleans())
    def run(kind: str, force: bool) -> None:
        out = tmp_path / "plan-out.yaml"
        for p in (out, tmp_path / "chain"):
            if p.is_symlink() or p.is_file():
                p.unlink()
            elif p.is_dir():
                p.rmdir()
        victim.write_text("keep me")
        if kind == "existing":
            out.write_text("old plan")
        elif kind == "link-to-file":
            out.symlink_to(victim)
        elif kind == "dangling-link":
            out.symlink_to(tmp_path / "nowhere.yaml")
        elif kind == "link-to-dir":
            out.symlink_to(tmp_path)
        elif kind == "dir":
            out.mkdir()
        elif kind == "link-to-link":
            (tmp_path / "chain").symlink_to(victim)
            out.symlink_to(tmp_path / "chain")

        def call() -> str:
            try:
                write_new(out, "name: p\n", force)
            except UserError as e:
                raise ConfigError(str(e)) from None
            return out.read_text()

        valid = kind == "new" or (kind == "existing" and force)
        result = outcome(call, out, valid, lambda text: text == "name: p\n")
        if victim.read_text() != "keep me" or (tmp_path / "nowhere.yaml").exists():
            result = ("wrong acceptance", "written through the link")
        tally.add(result, (kind, force))

    run()
    tally.verdict()


# ----------------------------------------------------------------------- rumba gcode axis

_AXIS = st.lists(st.one_of(st.sampled_from([0.0, -0.0, 1.0, -1.0, 1e-12, 1e-300, 0.5]),
                           st.floats(allow_nan=True, allow_infinity=True)),
                 min_size=3, max_size=3)


def test_gcode_on_a_spindle_axis_that_is_no_direction(tmp_path: Path) -> None:
    """`rumba gcode` end to end (it crashed on ``spindle_axis: [0,0,0]``): exit 0 with a
    program, or exit 2 and one ``error:`` line naming the machine file."""
    from daemon.cli.main import main

    tally = Tally("gcode spindle_axis")
    base = yaml.safe_load((CONFIG / "machines/thesis_wcbxfzyt.yaml").read_text())

    @FUZZ
    @given(v=_AXIS)
    def run(v: list[float]) -> None:
        doc = copy.deepcopy(base)
        doc["tool"]["spindle_axis"] = v
        path = tmp_path / "m.yaml"
        path.write_text(yaml.safe_dump(doc))
        out = tmp_path / "p.nc"
        out.unlink(missing_ok=True)
        a = np.asarray(v, float)
        with np.errstate(all="ignore"):
            ok = bool(np.isfinite(a).all() and np.linalg.norm(a) >= 1e-9)

        def call() -> int:
            err = io.StringIO()
            with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
                code = main(["gcode", "--machine", str(path), "--artefact",
                             str(CONFIG / "artefacts/thesis_4ball.yaml"), "--plan",
                             str(CONFIG / "plans/thesis_ch3_7poses.yaml"), "--dialect",
                             "fanuc", "-o", str(out)])
            text = err.getvalue().strip()
            if code == 2 and text.count("\n") == 0 and text.startswith("error: "):
                if not ok and str(path) not in text:
                    raise RuntimeError(f"refused without naming the machine file: {text}")
                raise ConfigError(f"{path}: {text.removeprefix('error: ')}")
            if code != 0:
                raise RuntimeError(f"exit {code}: {text[-300:]}")
            return code

        # a tilted spindle axis may still be refused (the program leaves travel): either
        tally.add(outcome(call, path, False if not ok else None, lambda _: out.is_file()),
                  v)

    run()
    tally.verdict()
