"""Property-based fuzzing of the other issue-20 input surfaces: who confirms a compensation
(``--by``, HMI names), the plan name, ``rumba plan -o`` and ``--max-time``, ``rumba gcode`` on
a spindle axis that is no direction, an MQTT password without TLS, the fleet page's paths and
the garbage a fleet store may hold. Classified and counted as in tests/test_inputs_fuzz.py
(``tests.input_fuzz_helpers``); ``benchmarks/fuzz/inputs.py`` runs the same tests longer."""

from __future__ import annotations

import asyncio
import contextlib
import copy
import io
import json
import math
import re
import socket
import threading
import unicodedata
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from hypothesis import example, given
from hypothesis import strategies as st

from contracts.plan_targets import load_targets_file
from contracts.yaml_files import ConfigError
from daemon.compensation.names import BadName, validate_by
from tests.input_fuzz_helpers import Tally, outcome
from tests.reader_helpers import CONFIG
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
    from contracts.centres_file import read_centres, write_centres
    from tests.input_fuzz_helpers import EXAMPLE_LOG, READERS
    from tests.reader_helpers import centre_rows

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


# ---------------------------------------------------------------------- MQTT credentials

_LOOPBACK = ["127.0.0.1", "127.0.0.53", "127.255.255.254", "::1", "localhost"]
_AMBIGUOUS = ["LOCALHOST", "localhost.", "127.1", "0x7f000001", "::ffff:127.0.0.1",
              "0:0:0:0:0:0:0:1", "2130706433", "0177.0.0.1"]
_REMOTE = ["192.0.2.1", "broker.example", "10.0.0.1", "0.0.0.0", "::", "fe80::1",
           "localhost.example", "127.0.0.1.nip.io", "local host", "localhost\x00", "[::1]",
           "1.2.3.4 ", "xn--lcalhost-8ya", "lоcalhost"]


def test_an_mqtt_password_crosses_a_network_only_inside_tls(tmp_path: Path) -> None:
    from daemon.config import load_daemon_config
    from tests.daemon_helpers import write_daemon_yaml

    tally = Tally("mqtt password / TLS")
    secret = tmp_path / "mqtt.pw"
    secret.write_text("pw-0123456789abcdef")
    secret.chmod(0o600)

    @FUZZ
    @given(host=st.one_of(st.sampled_from(_LOOPBACK + _AMBIGUOUS + _REMOTE),
                          st.text(max_size=20)), tls=st.booleans(), password=st.booleans())
    def run(host: str, tls: bool, password: bool) -> None:
        section = {"host": host, "site": "plant1"}
        if password:
            section |= {"username": "rumba", "password_file": str(secret)}
        if tls:
            section["tls"] = {}
        path = write_daemon_yaml(tmp_path, extra_top=yaml.safe_dump({"mqtt": section}))
        if password and not tls:
            valid = True if host in _LOOPBACK else (None if host in _AMBIGUOUS else False)
        else:
            valid = None  # other rules (host syntax) may refuse it
        tally.add(outcome(lambda: load_daemon_config(path), path, valid),
                  (host, tls, password))

    run()
    tally.verdict()


# ---------------------------------------------------------------------------- fleet page


@contextlib.contextmanager
def _fleet_page(token: str) -> Iterator[tuple[int, asyncio.AbstractEventLoop]]:
    """The real fleet page on a free loopback port, its store a closed loopback port (every
    read is 'unreachable'), in an event loop of its own thread."""
    from aiohttp import web

    from daemon.fleet.app import create_fleet_app

    with socket.socket() as s:  # a port nobody listens on: the store refuses at once
        s.bind(("127.0.0.1", 0))
        dead = s.getsockname()[1]
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    app = create_fleet_app(f"postgresql://rumba@127.0.0.1:{dead}/fleet", token,
                           bind_host="127.0.0.1")
    runner = web.AppRunner(app, handle_signals=False)

    async def start() -> int:
        await runner.setup()
        site = web.TCPSite(runner, "127.0.0.1", 0)
        await site.start()
        return int(runner.addresses[0][1])

    port = asyncio.run_coroutine_threadsafe(start(), loop).result(30)
    try:
        yield port, loop
    finally:
        asyncio.run_coroutine_threadsafe(runner.cleanup(), loop).result(30)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(10)
        loop.close()


_SEGMENT = st.one_of(st.sampled_from(["mill-a", "%00", "mill-a%00", "a%0Ab", "%E2%80%AE",
                                      "x" * 33, "x" * 32, "..", ".", "%2e%2e", "a%2Fb",
                                      "%ff", "mill%20a", "ｍill", "mill.a", "-", "_"]),
                     st.text(st.characters(codec="ascii", exclude_characters="/?#"),
                             min_size=1, max_size=40).map(
                         lambda t: "".join(c if c.isalnum() or c in "-._~" else
                                           f"%{ord(c):02X}" for c in t)))


def test_fleet_page_paths_answer_404_or_the_store_state_never_500() -> None:
    import urllib.error
    import urllib.request
    from urllib.parse import quote, unquote

    token = "t0k3n-for-the-fleet-fuzz-0123"
    tally = Tally("fleet page paths")
    opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))  # loopback, direct
    with _fleet_page(token) as (port, _):

        @FUZZ
        @given(segment=_SEGMENT)
        def run(segment: str) -> None:
            url = f"http://127.0.0.1:{port}/machines/{quote(segment, safe='%-._~')}"
            req = urllib.request.Request(url, headers={"Authorization": f"Bearer {token}"})

            def call() -> int:
                try:
                    with opener.open(req, timeout=8) as r:
                        return int(r.status)
                except urllib.error.HTTPError as e:
                    if e.code == 404:
                        raise ConfigError(f"{url}: 404") from None
                    return int(e.code)

            name = unquote(segment, errors="replace")  # invalid UTF-8: U+FFFD, unsafe
            safe = bool(re.fullmatch(r"[A-Za-z0-9_.-]{1,32}", name, re.ASCII)) and \
                name.strip(".") != ""
            # a safe name reaches the (unreachable) store: 503; anything else is 404
            tally.add(outcome(call, url, safe, lambda s: s == 503),
                      segment)

        run()
    tally.verdict()


_JSON = st.recursive(
    st.one_of(st.none(), st.booleans(), st.floats(allow_nan=True, allow_infinity=True),
              st.integers(-10**20, 10**20), st.integers(-10**400, 10**400),
              st.sampled_from([3.9e16, -3.9e16, 1.7e308, -1.7e308, 1e12, 32503680001.0, -1e11]),
              st.text(max_size=8)),
    lambda inner: st.one_of(st.lists(inner, max_size=4),
                            st.dictionaries(st.sampled_from(["value", "unit", "warn", "fail",
                                                             "links", "default_um",
                                                             "default_urad", "EX0C", "EB0Z",
                                                             "x"]), inner, max_size=4)),
    max_leaves=12)


def test_garbage_in_the_fleet_store_never_costs_the_page() -> None:
    from daemon.fleet import view

    tally = Tally("fleet stored garbage")

    @FUZZ
    @given(limits=_JSON, links=_JSON, started=_JSON, unit=st.sampled_from(["um", "urad", "x"]),
           value=_JSON)
    # found by the longer run (benchmarks/fuzz/inputs.py): a time and a value of 1e16 made
    # the chart's y range zero (ZeroDivisionError), an integer beyond a float overflowed
    @example(limits={}, links={}, started=3.883284668996908e16, unit="um",
             value=3.883284668996908e16)
    @example(limits={"default_um": {"warn": 10**400, "fail": -1.7e308}}, links={},
             started=-1e11, unit="um", value=10**400)
    @example(limits={"default_urad": {"warn": 1.7e308}}, links={}, started=1.7e9, unit="urad",
             value=-1.7e308)
    def run(limits: Any, links: Any, started: Any, unit: str, value: Any) -> None:
        trend = [{"run_id": "r1", "started_at": started, "verdict": "PASS", "links": links},
                 {"run_id": "r2", "started_at": 1.7e9, "verdict": "WARN",
                  "links": {"EX0C": {"value": value, "unit": unit}}}]
        runs = [{"id": "r1", "started_at": started if isinstance(started, float) else 1.7e9,
                 "trigger": "cli", "state": "DONE", "verdict": "PASS", "summary": "<b>",
                 "has_report": True}]

        def call() -> str:
            return view.machine_page("mill-x", {"limits": limits}, runs, trend, 90)

        def check(page: str) -> bool:  # a page, the garbage never as markup, no NaN drawn
            return (page.startswith("<!") and "<b>" not in page
                    and not re.search(r"(?<![\w])-?(nan|inf)(?![\w])", page, re.I))

        tally.add(outcome(call, "store", True, check),
                  json.dumps([limits, links, started, value], default=str)[:300])

    run()
    tally.verdict()
