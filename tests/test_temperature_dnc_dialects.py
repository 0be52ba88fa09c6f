"""Temperature channels over plain DNC for every dialect that can print: the
program prints the control's variable (Fanuc/Haas ``DPRNT`` of a common variable, 840D ``WRITE``
of a string chain, TNC ``FN 16: F-PRINT`` with a fixed format file) beside its result lines, the
DNC link parses the ``RTEMP`` lines and the daemon journals them; end to end over a real pty
against the simulated control's serial front-end. LinuxCNC prints nothing on a serial line:
refused with the alternative. The parsed line is fuzzed: no traceback, nothing accepted that the
grammar does not allow."""

from __future__ import annotations

import math
import re

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from benchmarks.rigs.e2e_run import copy_aux_files
from benchmarks.rigs.temperature_helpers import run_from_cnc
from benchmarks.rigs.warm_cnc import machine_entry, sensor, write_config
from contracts.dialects import dialect
from contracts.temperatures import PRINTED_RANGE_C, parse_printed
from contracts.yaml_files import ConfigError
from daemon.config import load_daemon_config
from daemon.run.session import State
from programs.dialects import get_dialect
from programs.geometry import ProgramError
from programs.model import Program
from simulators import thermal
from tests.test_temperature_channels import cnc

__all__ = ["cnc"]  # the warming CNC fixture, shared with the channels' end-to-end tests

VARIABLE = {"fanuc": thermal.FANUC_VARIABLE, "haas": thermal.FANUC_VARIABLE,
            "siemens": thermal.SIEMENS_VARIABLE, "heidenhain": thermal.HEIDENHAIN_VARIABLE}


@pytest.mark.asyncio
@pytest.mark.parametrize("cnc", ["serial-pty"], indirect=True)
@pytest.mark.parametrize("dialect", ["fanuc", "haas", "siemens", "heidenhain"])
async def test_dnc_program_prints_the_variable_in_every_dialect_that_can(cnc, tmp_path,
                                                                         dialect):
    """Over plain DNC nothing can be polled: the program prints the control's variable at the
    start, at every pose and at the end (``RTEMP`` lines), the link parses them beside the
    result lines."""
    rig, _, port = cnc
    rig.ctrl.dialect = dialect
    var = VARIABLE[dialect]["Z"]
    channels = [{"name": "spindle", "address": var},
                {"name": "column", "source": "transmitter", "address": "input:0",
                 "scale": 0.1, "transmitter": {"host": "127.0.0.1", "port": port}}]
    entry = machine_entry(rig.link, channels, {})
    entry["dialect"] = dialect
    cfg = load_daemon_config(write_config(tmp_path, entry))
    if dialect == "heidenhain":  # the format files, copied to the TNC once
        copy_aux_files(rig.ctrl, cfg.machines["mill1"])
        assert {"RTEMP_S.A", "RTEMP_P.A", "RTEMP_E.A"} <= set(rig.ctrl.files)
    run = await run_from_cnc(cfg, rig.ctrl)
    assert run.session.state == State.IDLE, run.session.reason
    readings, analysis = run.readings, run.analysis
    spindle = [r for r in readings if r.channel == "spindle"]
    assert [(r.at, r.pose) for r in spindle] == [
        ("start", None), *[("pose", p) for p in range(7)], ("end", None)], spindle
    values = [r.value_c for r in spindle]
    assert values[0] == pytest.approx(sensor("Z", 0.0), abs=5e-4)  # 3 decimals printed
    assert values == sorted(values) and values[-1] - values[0] > 1.0, values
    lo, hi = sensor("Z", 0.0), sensor("Z", 1e9)  # each on the warm-up curve the touches drift on
    assert all(lo - 5e-4 <= v <= hi + 5e-4 for v in values)
    column = [r for r in readings if r.channel == "column"]
    assert [r.at for r in column] == ["start", *["pose"] * 7, "end"]
    assert analysis.temperatures["spindle"]["source"] == f"spindle: serial {var}"
    assert analysis.temperatures["spindle"]["unread"] == 0


@pytest.mark.parametrize(("dialect", "address", "message"), [
    ("linuxcnc", "#5021", "LinuxCNC prints nothing on a serial line"),
    ("linuxcnc", "rumba-probe.temp-z", "read the channel as a HAL pin over the linuxcnc "
     "transport, or use source: transmitter"),
    ("fanuc", "#599", "is not a Fanuc common variable #100-#199, #500-#597 or #700-#999"),
    ("haas", "#5021", "is not a Fanuc common variable"),
    ("siemens", "R4", "is not a Sinumerik R parameter R5-R98"),
    ("siemens", "R99", "is not a Sinumerik R parameter R5-R98"),
    ("siemens", "R100", "is not a Sinumerik R parameter R5-R98"),
    ("siemens", "$A_INA[1]", "is not a Sinumerik R parameter R5-R98"),
    ("heidenhain", "Q115", "is not a Heidenhain Q parameter Q0-Q99"),
    ("heidenhain", "Q1599", "is not a Heidenhain Q parameter Q0-Q99"),
    ("heidenhain", "QR5", "is not a Heidenhain Q parameter Q0-Q99"),
])
def test_dnc_channel_config_refuses_what_the_control_cannot_print(tmp_path, dialect, address,
                                                                  message):
    link = {"transport": "serial", "url": "/dev/ttyS0", "baudrate": 9600}
    entry = machine_entry(link, [{"name": "spindle", "address": address}], {})
    entry["dialect"] = dialect
    with pytest.raises(ConfigError) as e:
        load_daemon_config(write_config(tmp_path, entry))
    text = str(e.value)
    assert "machines.0.temperatures.0.address" in text and message in text, text
    assert "\n" not in text.strip()


@pytest.mark.parametrize("dialect", ["siemens", "heidenhain"])
def test_only_a_user_variable_reaches_the_program_text(dialect):
    """The variable is checked again when the program is rendered: an injection that got past
    the config (or a caller without one) is refused, never printed."""
    prog = Program.__new__(Program)
    bad = ['R5"<<M30', "R5\nM30", "Q5 ; M30", "R4", "R99", "Q1598", "Q1599", "Q115", "#593",
           "R5 ", "q5", "r5", "R05", "Q100"]
    for b in bad:
        prog.temperature_vars = (b,)
        with pytest.raises(ProgramError, match=f"is not a {dialect} variable"):
            get_dialect(dialect).temperature_prints(prog)
    good = {"siemens": ("R5", "R91", "R98"), "heidenhain": ("Q0", "Q91", "Q99")}[dialect]
    prog.temperature_vars = good
    assert [t["var"] for t in get_dialect(dialect).temperature_prints(prog)] == list(good)


def test_the_variable_ranges_leave_rumbas_own_alone():
    """No printable variable is one rumba writes (verdict, counter, ring, print copies)."""
    own = {"fanuc": ["#598", "#599", *[f"#{600 + i}" for i in range(88)]],
           "siemens": ["R4", "R99", *[f"R{100 + i}" for i in range(88)]],
           "heidenhain": ["Q1598", "Q1599", *[f"Q{1575 + i}" for i in range(19)],
                          *[f"Q{1600 + i}" for i in range(88)], *[f"Q{115 + i}" for i in range(5)]]}
    own["haas"] = own["fanuc"]
    for family, names in own.items():
        assert not [n for n in names if dialect(family).prints_temperature(n)], family


# ------------------------------------------------------------------------------------ fuzz
_ORACLE_VALUE = re.compile(r"-?[0-9]{1,5}(\.[0-9]{1,6})?")


def oracle(line: str) -> tuple[int, str, float] | None:
    """The grammar written out by hand: what parse_printed must accept, and nothing more."""
    body = line.strip(" \t\r\n")
    parts = body.split(" ")
    parts = [p for p in parts if p != ""]
    if " ".join(parts) != re.sub(" +", " ", body) or len(parts) != 4 or parts[0] != "RTEMP":
        return None
    _, marker, k, value = parts
    if not (marker in ("S", "E") or (marker[:1] == "P" and 2 <= len(marker) <= 5
                                      and all(c in "0123456789" for c in marker[1:]))):
        return None
    if not (1 <= len(k) <= 2 and all(c in "0123456789" for c in k)) or int(k) == 0:
        return None
    if not all(c in "-.0123456789" for c in value) or not _ORACLE_VALUE.fullmatch(value):
        return None
    v = float(value)
    if not PRINTED_RANGE_C[0] <= v <= PRINTED_RANGE_C[1]:
        return None
    return int(k), marker, v


def check(line: str) -> None:
    want = oracle(line)
    try:
        got = parse_printed(line)
    except ValueError as e:
        assert want is None, (line, want, e)  # refused a good line
        assert "temperature line" in str(e)
        return
    assert want is not None, (line, got)  # a wrong acceptance
    assert got == want and math.isfinite(got[2])


valid = st.builds(
    lambda marker, k, v, pad, eol: (f"RTEMP{pad}{marker}{pad}{k}{pad}{v}{eol}"),
    st.one_of(st.sampled_from(["S", "E"]), st.integers(0, 9999).map(lambda p: f"P{p}")),
    st.integers(1, 99),
    st.one_of(st.decimals(-60, 200, places=3).map(str),
              st.integers(-60, 200).map(str),
              st.floats(-60, 200).map(lambda f: f"{f:.6f}")),
    st.sampled_from([" ", "  ", "   "]), st.sampled_from(["", "\r\n", "\n", " "]))


@settings(max_examples=600, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(valid)
def test_fuzz_valid_lines_parse_exactly(line):
    assert oracle(line) is not None, line  # the generator makes only good lines
    check(line)


@settings(max_examples=1500, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(valid, st.integers(0, 40), st.text(min_size=0, max_size=4), st.booleans())
def test_fuzz_mutated_lines_no_traceback_no_wrong_acceptance(line, at, junk, delete):
    at = min(at, len(line))
    mutated = line[:at] + line[at + len(junk):] if delete else line[:at] + junk + line[at:]
    check(mutated)


@settings(max_examples=800, deadline=None)
@given(st.text(max_size=80))
def test_fuzz_any_text_no_traceback_no_wrong_acceptance(text):
    check(text)
    check("RTEMP " + text)
