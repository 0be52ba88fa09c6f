"""The dialect records: each registered dialect is complete (template, program writer, goldens,
interpreter, compensation writer), and a dialect added as one record reaches every layer."""

from __future__ import annotations

import dataclasses
import re

import pytest
from pydantic import ValidationError

from benchmarks.rigs.sim_helpers import truth_with
from contracts.dialects import DIALECTS, KINEMATICS_ADDRESSES, DialectRecord, dialect, load
from contracts.setup_files import machine_from_dict, plan_from_dict
from contracts.temperatures import TemperatureChannel, check_address
from contracts.yaml_files import format_validation
from daemon.machines.setup import MachineEntry
from programs.compensation import fanuc as fanuc_compensation
from programs.compensation import writer
from programs.dialects import Dialect, get_dialect
from programs.dialects.base import TEMPLATES
from programs.generate import generate
from programs.toolpath import build_program
from simulators.gcode import make_interpreter
from simulators.gcode.core import Interpreter
from simulators.offline import run_program
from tests.compensation_helpers import THESIS, pivot, read_doc
from tests.regen_golden import GOLDEN, golden_setup

PLAN = {"name": "records", "stylus_diameter_mm": 6, "poses": [[0, 0]]}


@pytest.fixture
def acme(monkeypatch) -> DialectRecord:
    """A throw-away dialect: one record, reusing the fanuc family's template and writers."""
    rec = dataclasses.replace(DIALECTS["fanuc"], name="acme")
    monkeypatch.setitem(DIALECTS, "acme", rec)
    return rec


def _entry(dialect_name: str) -> dict:
    return {"name": "m1", "machine": "m.yaml", "artefact": "a.yaml", "plan": "p.yaml",
            "dialect": dialect_name, "link": {"transport": "serial", "port": "/dev/ttyS0"}}


# ------------------------------------------------------------------- every record complete
@pytest.mark.parametrize("name", list(DIALECTS))
def test_every_record_is_complete(name):
    rec = dialect(name)
    assert rec.name == name
    cls = load(rec.program)
    assert issubclass(cls, Dialect) and cls.name == rec.family
    assert (TEMPLATES / rec.family / "program.j2").is_file()
    assert (GOLDEN / f"{rec.family}.{cls.extension}").is_file()
    assert issubclass(load(rec.interpreter), Interpreter)
    assert callable(load(rec.compensation_writer))
    assert rec.kinematics_address in KINEMATICS_ADDRESSES
    # a printable temperature is never one of rumba's own variables
    own = [rec.verdict_variable, rec.result_counter, *(rec.handshake_variables or ())]
    assert not [v for v in own if rec.prints_temperature(v)]
    if rec.temperature_variable is not None:
        re.compile(rec.temperature_variable)
        assert rec.temperature_form
    assert not (rec.handshake_variables and rec.stop_program)


@pytest.mark.parametrize("name", list(DIALECTS))
async def test_the_simulator_runs_every_dialects_program(name):
    """What the program writer of each record emits, its simulated control executes."""
    truth = truth_with({})
    prog = build_program(truth.machine, truth.machine_file, truth.artefact,
                         plan_from_dict(PLAN))
    d = get_dialect(name)
    assert d.label == name
    res = await run_program(truth, d.render(prog), name, files=d.aux_files(prog), seed=1,
                            timeout_s=120)
    assert res.state == "done", res.alarm
    assert len(res.rows) == len(prog.touches)


def test_an_unknown_dialect_is_refused_naming_the_known_ones():
    with pytest.raises(ValueError, match=r"unknown dialect 'okuma' \(known: fanuc, haas"):
        dialect("okuma")
    with pytest.raises(ValidationError) as e:
        MachineEntry.model_validate(_entry("okuma"))
    assert format_validation("daemon.yaml", e.value) == (
        "daemon.yaml: dialect: Input should be 'fanuc', 'haas', 'siemens', 'heidenhain' or "
        "'linuxcnc'")


# ------------------------------------------------------------- a dialect added as one record
def test_a_new_record_reaches_the_schemas(acme):
    assert MachineEntry.model_validate(_entry("acme")).dialect == "acme"
    with pytest.raises(ValidationError, match="'linuxcnc' or 'acme'"):
        MachineEntry.model_validate(_entry("okuma"))
    doc = read_doc(THESIS)
    doc["controller_kinematics"] = {"family": "acme", "params": [pivot("x", "19700", 0.5)]}
    _, mf = machine_from_dict(doc, "m.yaml")
    assert mf.controller_kinematics.family == "acme"


def test_a_new_record_reaches_the_program_writer(acme):
    """The acme program is the fanuc family's, named acme in its header."""
    got = generate(*golden_setup(), "acme").text.splitlines()
    want = (GOLDEN / "fanuc.nc").read_text(encoding="ascii").splitlines()
    assert [(a, b) for a, b in zip(got, want, strict=True) if a != b] == [
        ("(DIALECT ACME)", "(DIALECT FANUC)")]


async def test_a_new_record_reaches_the_simulator(acme):
    truth = truth_with({})
    prog = build_program(truth.machine, truth.machine_file, truth.artefact,
                         plan_from_dict(PLAN))
    prog.handshake = True  # the record's ring handshake reaches the program
    assert "#688" in get_dialect("acme").render(prog)
    prog.handshake = False  # (no link acks here: a full ring would wait)
    assert make_interpreter("acme", truth).name == "acme"
    res = await run_program(truth, get_dialect("acme").render(prog), "acme", seed=1,
                            timeout_s=120)
    assert res.state == "done", res.alarm
    assert len(res.rows) == len(prog.touches)
    res.controller.verdict = 2  # a front-end writing the verdict: the record's variable shows it
    assert res.controller.variables[acme.verdict_variable] == 2.0


def test_a_new_record_reaches_temperatures(acme):
    ch = TemperatureChannel(name="spindle", address="#100")
    check_address(ch, "serial", "acme")
    with pytest.raises(ValueError, match="is not a Fanuc common variable"):
        check_address(TemperatureChannel(name="spindle", address="R5"), "serial", "acme")
    quiet = dataclasses.replace(acme, temperature_variable=None,
                                temperature_refusal="acme prints nothing")
    DIALECTS["acme"] = quiet
    with pytest.raises(ValueError, match="acme prints nothing"):
        check_address(ch, "serial", "acme")


def test_a_new_record_reaches_controller_kinematics_and_compensation(acme):
    from contracts.controller_kinematics import controller_kinematics

    doc = read_doc(THESIS)
    doc["controller_kinematics"] = {"family": "acme", "params": [pivot("x", "P19700", 0.5)]}
    with pytest.raises(Exception, match="neither a parameter number"):
        machine_from_dict(doc, "m.yaml")
    doc["controller_kinematics"]["params"] = [pivot("x", "19700", 0.5)]
    m, mf = machine_from_dict(doc, "m.yaml")
    spec = controller_kinematics(mf.controller_kinematics, m, "m.yaml")
    assert spec.family == "acme" and spec.params[0].address == "19700"
    assert writer("acme") is fanuc_compensation.render
    # a control without orientation parameters: the record says so, the section refuses one
    DIALECTS["acme"] = dataclasses.replace(acme, kinematics_orientation=False)
    doc["controller_kinematics"]["params"] = [
        {"name": "t", "kind": "orientation", "component": "EA0C", "address": "19743",
         "value": 0.0}]
    with pytest.raises(Exception, match="a acme control has no orientation parameter"):
        machine_from_dict(doc, "m.yaml")


# ------------------------------------------------------------------ no switch on the names
_NAMES = "|".join(DIALECTS)
_SWITCH = re.compile(rf"""(==|!=)\s*["']({_NAMES})["']|\bin\s*\(\s*["']({_NAMES})["']""")
# a link checks the dialect it runs by name: it is that control's own file, not a switch
# between dialects; a transport of the same name (linuxcnc, haas) is not a dialect, nor is
# the simulator's --serve choice of a transport front-end
_OWN = ("drivers/", "simulators/linuxcnc_peer.py", "simulators/serve.py")


def test_no_layer_switches_on_dialect_names():
    """Every layer reads the record: a comparison with a dialect's name outside the files of
    one control is a switch a new dialect would have to find."""
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    found = []
    for pkg in ("contracts", "programs", "simulators", "daemon", "identification"):
        for path in sorted((root / pkg).rglob("*.py")):
            rel = path.relative_to(root).as_posix()
            if rel == "contracts/dialects.py" or rel.startswith(_OWN):
                continue
            for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
                if _SWITCH.search(line) and "transport" not in line:
                    found.append(f"{rel}:{n}: {line.strip()}")
    assert found == []
