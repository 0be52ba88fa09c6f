"""G-code name injection: every name that reaches a program (machine, plan, artefact, ball ids,
keep-out boxes, daemon machine entries, the serial request name) is refused at load time when
it could break out of a comment or message, and a name that bypassed validation is refused by
every dialect's renderer; a per-dialect checker proves accepted names stay inside one closed
comment / message / file name on one line."""

from __future__ import annotations

import copy
import re
from dataclasses import replace
from pathlib import Path

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from contracts.result_lines import DIALECT_NAMES
from contracts.setup_files import (
    artefact_from_dict,
    load_machine,
    machine_from_dict,
    plan_from_dict,
)
from contracts.yaml_files import ConfigError
from daemon.config import config_from_dict
from drivers.registry import link_config
from programs.dialects import get_dialect
from programs.geometry import ProgramError
from programs.model import Program
from programs.toolpath import build_program
from tests.regen_golden import golden_program

ROOT = Path(__file__).resolve().parent.parent
CONFIG = ROOT / "config"
DIALECTS = list(DIALECT_NAMES)
BAD = ["abc\n", "abc\r", "abc\r\n", "\nabc", "ab\x00c", "ab\u2028c", "ab\x85c", "ab(c", "ab)c",
       "ab;c", "ab%c", "ab'c", 'ab"c', "ab c", "ab\tc", "ab,c", "abc)\nM30\n(", "B1\x0b"]
PLACEHOLDER = "ZQ9"  # a name fanuc can print too (upper case, no '_')


def _yaml(rel: str) -> dict:
    return yaml.safe_load((CONFIG / rel).read_text(encoding="utf-8"))


def _set(data: dict, dotted: str, value: object) -> dict:
    data = copy.deepcopy(data)
    node = data
    keys = [int(k) if k.isdigit() else k for k in dotted.split(".")]
    for k in keys[:-1]:
        node = node[k]
    node[keys[-1]] = value
    return data


def _machine_with_box(name: str) -> dict:
    data = _yaml("machines/thesis_wcbxfzyt.yaml")
    data["keep_out"] = [{"name": name, "min_mm": [0, 0, 0], "max_mm": [1, 1, 1]}]
    return data


# field → (loader of one value, key the error must name)
LOADERS = {
    "machine name": (lambda v: machine_from_dict(
        _set(_yaml("machines/thesis_wcbxfzyt.yaml"), "name", v), "m.yaml"), "m.yaml: name:"),
    "keep-out name": (lambda v: machine_from_dict(_machine_with_box(v), "m.yaml"),
                      "m.yaml: keep_out.0.name:"),
    "artefact name": (lambda v: artefact_from_dict(
        _set(_yaml("artefacts/thesis_4ball.yaml"), "name", v), "a.yaml"), "a.yaml: name:"),
    "ball id": (lambda v: artefact_from_dict(
        _set(_yaml("artefacts/thesis_4ball.yaml"), "balls.0.id", v), "a.yaml"),
        "a.yaml: balls.0.id:"),
    "plan name": (lambda v: plan_from_dict(
        _set(_yaml("plans/thesis_ch3_7poses.yaml"), "name", v), "p.yaml"), "p.yaml: name:"),
    "daemon machine name": (lambda v: config_from_dict(
        _set(_yaml("daemon.yaml"), "machines.0.name", v), Path("d.yaml")),
        "d.yaml: machines.0.name:"),
    "serial request name": (lambda v: link_config(
        {"transport": "serial", "url": "/dev/ttyS0", "request_machine": v}, "link"),
        "link: request_machine:"),
}


@pytest.mark.parametrize("bad", BAD, ids=repr)
@pytest.mark.parametrize("field", sorted(LOADERS))
def test_loaders_refuse_names_that_could_break_out(field, bad):
    load, key = LOADERS[field]
    with pytest.raises(ConfigError) as info:
        load(bad)
    msg = str(info.value)
    assert key in msg
    assert len(msg.splitlines()) == 1 and msg.isprintable()


@pytest.mark.parametrize("field", sorted(LOADERS))
def test_loaders_accept_a_safe_name(field):
    LOADERS[field][0]("Machine-1.b_2")


GOLDEN = golden_program()


def _with_name(prog: Program, field: str, name: str) -> Program:
    """The golden program with one name replaced after validation (a bypass)."""
    prog = copy.copy(prog)
    if field == "plan":
        prog.plan = prog.plan.model_copy(update={"name": name})
    elif field == "machine":
        prog.machine = replace(prog.machine, name=name)
    elif field == "artefact":
        prog.artefact = replace(prog.artefact, name=name)
    else:
        old = prog.artefact.balls[0].id
        balls = (replace(prog.artefact.balls[0], id=name), *prog.artefact.balls[1:])
        prog.artefact = replace(prog.artefact, balls=balls)
        prog.touches = [replace(t, id=replace(t.id, ball=name)) if t.id.ball == old else t
                        for t in prog.touches]
        prog.moves = [replace(m, touch=next(t for t in prog.touches if t.id.seq == m.touch.id.seq))
                      if m.touch is not None else m for m in prog.moves]
    return prog


FIELDS = ["plan", "machine", "artefact", "ball"]


@pytest.mark.parametrize("bad", BAD, ids=repr)
@pytest.mark.parametrize("field", FIELDS)
@pytest.mark.parametrize("dialect", DIALECTS)
def test_every_dialect_refuses_a_name_that_bypassed_validation(dialect, field, bad):
    prog = _with_name(GOLDEN, field, bad)
    d = _DIALECT[dialect]
    with pytest.raises(ProgramError):
        d.render(prog)
    if dialect == "heidenhain" and field == "ball":  # its format files are named after balls
        with pytest.raises(ProgramError):
            d.aux_files(prog)


@pytest.mark.parametrize("bad", BAD, ids=repr)
def test_build_program_refuses_an_unsafe_ball_id(bad):
    g = GOLDEN
    art = replace(g.artefact, balls=(replace(g.artefact.balls[0], id=bad),
                                     *g.artefact.balls[1:]))
    with pytest.raises(ProgramError, match="not a safe name"):
        build_program(g.machine, g.machine_file, art, g.plan)


# ------------------------------------------------------------------ per-dialect checker


def _paren_zones(line: str) -> list[tuple[int, int]]:
    """Comment spans of a Fanuc / LinuxCNC line; AssertionError when nested or unbalanced."""
    zones, start = [], None
    for i, ch in enumerate(line):
        if ch == "(":
            assert start is None, f"nested comment in {line!r}"
            start = i + 1
        elif ch == ")":
            assert start is not None, f"')' outside a comment in {line!r}"
            zones.append((start, i))
            start = None
    assert start is None, f"unclosed comment in {line!r}"
    return zones


def _quote_zones(line: str) -> list[tuple[int, int]]:
    """Spans inside double quotes, then the ';' comment (outside quotes) to the line end."""
    zones, start = [], None
    for i, ch in enumerate(line):
        if ch == '"':
            if start is None:
                start = i + 1
            else:
                zones.append((start, i))
                start = None
        elif ch == ";" and start is None:
            zones.append((i + 1, len(line)))
            break
    assert start is None, f"unclosed string in {line!r}"
    return zones


def _zones(dialect: str, line: str) -> list[tuple[int, int]]:
    """Where a name may stand in one program line of ``dialect`` (and the line is well formed)."""
    if dialect in ("fanuc", "haas", "linuxcnc"):
        assert "%" not in line or line == "%", f"tape mark inside {line!r}"
        zones = _paren_zones(line)
        if line.startswith("DPRNT[") and line.endswith("]"):
            zones.append((6, len(line) - 1))  # the printed text (ids are [A-Z0-9] there)
        return zones
    zones = _quote_zones(line)
    if dialect == "heidenhain":  # the F-PRINT format file name
        zones += [(m.start(1), m.end(1)) for m in re.finditer(r"RUMBA_([A-Za-z0-9_.-]+)\.A ", line)]
    return zones


def check_rendering(dialect: str, named: dict[str, str], placeholder: dict[str, str],
                    name: str) -> None:
    """``named`` / ``placeholder``: file name → text rendered with the name / with PLACEHOLDER.
    Same files and lines; a line that differs is the placeholder line with the name put in
    place, and every occurrence stands inside a closed comment / message / file name."""
    assert len(named) == len(placeholder)
    for fb, b in placeholder.items():
        fa = fb.replace(PLACEHOLDER, name)
        assert fa in named, f"file {fa!r} missing"
        a = named[fa]
        assert a.splitlines() == a.split("\n")[:-1], "a line break other than LF"
        la, lb = a.split("\n"), b.split("\n")
        assert len(la) == len(lb), "the name added or removed a line"
        for x, y in zip(la, lb, strict=True):
            if x == y:
                continue
            parts = y.split(PLACEHOLDER)
            assert len(parts) > 1, f"{x!r} differs from {y!r} without a name"
            cand = [n for n in (name, name.upper()) if n.join(parts) == x]
            assert cand, f"{x!r} is not {y!r} with the name in place"
            zones = _zones(dialect, x)
            pos = 0
            for p in parts[:-1]:
                pos += len(p)
                assert any(s <= pos and pos + len(cand[0]) <= e for s, e in zones), \
                    f"name {name!r} outside a comment or message in {x!r}"
                pos += len(cand[0])


_DIALECT = {name: get_dialect(name) for name in DIALECTS}


def _files(dialect: str, prog: Program) -> dict[str, str]:
    d = _DIALECT[dialect]
    return {"program": d.render(prog), **d.aux_files(prog)}


_REF = {(f, d): _files(d, _with_name(GOLDEN, f, PLACEHOLDER)) for f in FIELDS for d in DIALECTS}


@pytest.mark.parametrize("dialect", DIALECTS)
def test_checker_finds_a_broken_comment(dialect):
    ref = _files(dialect, _with_name(GOLDEN, "plan", PLACEHOLDER))
    bad = {k: v.replace(f"PLAN {PLACEHOLDER}", "PLAN X)\nM30\n(Y") for k, v in ref.items()}
    with pytest.raises(AssertionError):
        check_rendering(dialect, bad, ref, "X)\nM30\n(Y")
    assert check_rendering(dialect, ref, ref, PLACEHOLDER) is None


NAMES = st.one_of(st.text(max_size=40),
                  st.text(alphabet="AZaz09_.-() ;%\"'\n\r,:=+#[]*\x00\u2028", max_size=12),
                  st.from_regex(r"[A-Za-z0-9_.-]{1,32}", fullmatch=True))


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(field=st.sampled_from(FIELDS), name=NAMES)
def test_random_names_are_refused_or_stay_inside_a_comment(field, name):
    """Loaded: refused with ConfigError or accepted; accepted or not, put into a program (a
    bypass of validation) it is refused by the renderer or passes the checker in every dialect."""
    load = {"plan": "plan name", "machine": "machine name", "artefact": "artefact name",
            "ball": "ball id"}[field]
    try:
        LOADERS[load][0](name)
        accepted = True
    except ConfigError:
        accepted = False
    prog = _with_name(GOLDEN, field, name)
    for dialect in DIALECTS:
        ref = _REF[(field, dialect)]
        try:
            got = _files(dialect, prog)
        except ProgramError:
            # fanuc prints ball ids only as [A-Z0-9]{1,12}: an accepted id may still be refused
            assert not accepted or (field == "ball" and dialect in ("fanuc", "haas"))
            continue
        check_rendering(dialect, got, ref, name)


def test_shipped_machine_still_loads():
    m, mf = load_machine(CONFIG / "machines" / "thesis_wcbxfzyt.yaml")
    assert mf.name == m.name
