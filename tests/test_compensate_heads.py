"""Compensation write-back for the head families through the simulator: the
swivel head (Siemens tool carrier type M) and the fork head (type T) as shipped, and both with a
Heidenhain kinematics table and Fanuc 19700-series parameters; the rendered write-back reaches
the simulated control's values, a re-run identified against the controller model it now holds
measures the compensable links at zero, rollback restores every value. And why LinuxCNC's head
kins modules cannot take a compensation: their one pin, the pivot length, is not observable."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from contracts.setup_files import load_artefact, load_controller_kinematics, load_machine, load_plan
from identification.compensation import plan_compensation
from programs import compensation
from programs.dialects import get_dialect
from programs.toolpath import build_program
from simulators.controller import VirtualController
from simulators.errors_schema import errors_from_dict
from simulators.truth import TruthModel
from tests.sim_world import compensate_and_check, identify, sim_loop, sim_world  # noqa: F401

CFG = Path(__file__).resolve().parents[1] / "config"
ARTEFACT = CFG / "artefacts/vertical_4ball.yaml"  # as tests/test_head_families_e2e.py
HEADS = {
    "swivelhead": ("swivelhead_wcfxyzbt", "swivelhead_12poses"),
    "forkhead": ("forkhead_wxfyzcat", "forkhead_11poses"),
}
pytestmark = pytest.mark.usefixtures("sim_loop")
GUARDS = {"max_change_um": 200, "max_change_urad": 100, "max_total_um": 400}
# Each family's address of the shipped Siemens section's values, in the section's order
# (pivots first, then tilts): a Heidenhain kinematics table keeps a head axis' row (X Y Z of its
# transformation, SPA/SPB/SPC its spatial-angle correction), Fanuc 19700-series real parameters
# (machine file values in mm and deg; the numbers are the shop's assignment).
_ROWS = {"swivelhead": {"B": 5, "C": 2}, "forkhead": {"C": 4, "A": 5}}
_FANUC = ["19700", "19701", "19702", "19703", "19741", "19742", "19743", "19744"]


def _section(name: str, family: str) -> dict:
    """The shipped Siemens section of head ``name`` re-addressed for ``family``."""
    data = yaml.safe_load((CFG / f"machines/{HEADS[name][0]}.yaml").read_text(encoding="utf-8"))
    params = []
    for i, p in enumerate(data["controller_kinematics"]["params"]):
        q = {k: p[k] for k in ("name", "kind", "component") if k in p}
        if p["kind"] == "pivot":
            q.update(axes=p["axes"], value=p["value"])
            axis = p["axes"][0]  # the line it locates (the others ride on it)
            col = p["component"].upper()
        else:
            axis = p["component"][-1]
            col = "SP" + p["component"][1]
        q["address"] = f"{_ROWS[name][axis]}/{col}" if family == "heidenhain" else _FANUC[i]
        params.append(q)
    return {"family": family, "guards": GUARDS, "params": params}


def _machine_file(tmp: Path, name: str, family: str) -> Path:
    path = CFG / f"machines/{HEADS[name][0]}.yaml"
    if family == "siemens":
        return path
    data = yaml.safe_load(path.read_text(encoding="utf-8"))
    data["controller_kinematics"] = _section(name, family)
    out = tmp / f"{name}_{family}.yaml"
    out.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return out


# What each head's probing sees of its control's values (README: the rank computation).
OBSERVABLE = {"swivelhead": {"c-x", "b-tilt-a", "b-tilt-c", "c-tilt-a", "c-tilt-b"},
              "forkhead": {"a-y", "c-tilt-a", "c-tilt-b", "a-tilt-b", "a-tilt-c"}}


@pytest.mark.parametrize("family", ["siemens", "heidenhain", "fanuc"])
@pytest.mark.parametrize("name", sorted(HEADS))
def test_head_compensation_through_the_simulator(tmp_path: Path, name: str, family: str) -> None:
    w = sim_world(_machine_file(tmp_path, name, family), CFG / f"errors/{HEADS[name][0]}.yaml",
                  CFG / f"plans/{HEADS[name][1]}.yaml", ARTEFACT, family)
    # the probing sees exactly these values; the others are left, with the reason
    assert {ch.name for ch in w.plan1.changes if ch.observable} == OBSERVABLE[name]
    assert all(ch.note and ch.delta == 0.0 for ch in w.plan1.changes if not ch.observable)
    got, _ = compensate_and_check(w)
    # injected head/table location errors the control keeps, nearly whole (EA0B of the swivel
    # head shares its visible effect with EA0Z, which no carrier value holds)
    held = {"swivelhead": {"EX0C", "EA0C", "EB0C", "EA0B", "EC0B"},
            "forkhead": {"EA0C", "EB0C", "EY0A", "EB0A", "EC0A"}}[name]
    assert set(got) <= held and len(got) >= 4, w.plan1.links_compensable


def test_siemens_head_programs_name_the_carrier_values(tmp_path: Path) -> None:
    """The type T and M programs write head vectors (l2, v1) and close the chain on l1."""
    for name, addresses in (("swivelhead", ("$TC_CARR15[1]", "$TC_CARR18[1]", "$TC_CARR9[1]")),
                            ("forkhead", ("$TC_CARR16[1]", "$TC_CARR2[1]", "$TC_CARR12[1]"))):
        mpath = CFG / f"machines/{HEADS[name][0]}.yaml"
        _, spec = load_controller_kinematics(mpath)
        assert spec is not None
        from identification.compensation import ParamChange

        seen = [p.name in OBSERVABLE[name] for p in spec.params]
        changes = [ParamChange(p.name, p.kind, (0.01 if p.kind == "pivot" else 20e-6) * s, 0.0, s)
                   for p, s in zip(spec.params, seen, strict=True)]
        text = compensation.render(spec, changes, run_id="R1", machine=name).text
        for a in addresses:
            assert any(line.startswith(a + "=") for line in text.splitlines()), (a, text)
        # a value the probing cannot see keeps its value (the program restates it)
        hidden = {p.address for p in spec.params if p.name not in OBSERVABLE[name]}
        for line in text.splitlines():
            address, _, rest = line.partition("=")
            if address in hidden:
                new, old = rest.split(";")[0].strip(), rest.split(" old ")[1].strip()
                assert float(new) == float(old), line


def test_linuxcnc_head_kins_pivot_length_is_not_observable(tmp_path: Path) -> None:
    """LinuxCNC 2.9's head modules (5axiskins, maxkins) keep one geometry pin, the pivot length:
    the head's rotary axis line along the spindle. Moving it by dz moves the tip by
    (I − R)·dz·k: a constant (the balls' positions) plus −dz along the spindle in the tool frame
    (the probe's setup) — the probing cannot see it, so nothing can be written back to it."""
    data = yaml.safe_load((CFG / "machines/forkhead_wxfyzcat.yaml").read_text(encoding="utf-8"))
    data["controller_kinematics"] = {"family": "linuxcnc", "params": [
        {"name": "pivot-length", "kind": "pivot", "axes": ["C", "A"], "component": "z",
         "address": "5axiskins.pivot-length", "value": 230}]}
    mpath = tmp_path / "forkhead_linuxcnc.yaml"
    mpath.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    machine, mf = load_machine(mpath)
    _, spec = load_controller_kinematics(mpath)
    assert spec is not None
    artefact = load_artefact(ARTEFACT)
    plan = load_plan(CFG / "plans/forkhead_11poses.yaml")
    truth = TruthModel.build(machine, mf, artefact, errors_from_dict(yaml.safe_load(
        (CFG / "errors/forkhead_wxfyzcat.yaml").read_text())))
    d = get_dialect("linuxcnc")
    prog = build_program(machine, mf, artefact, plan)
    vc = VirtualController(truth, rng_seed=5, dialect="linuxcnc")
    est = identify(vc, "linuxcnc", d.render(prog), d.aux_files(prog), machine, artefact, "r")
    b = np.array([p.b_deg for p in plan.poses])
    c = np.array([p.c_deg for p in plan.poses])
    (ch,) = plan_compensation(machine, artefact, est, spec.to_math(), b, c).changes
    assert not ch.observable and ch.delta == 0.0
    assert "absorbed by the setup errors" in ch.note


@pytest.mark.parametrize("name, terms", [
    ("swivelhead", {"EX0C": "$TC_CARR15[1] (c-x)", "EA0B": "$TC_CARR9[1] (b-tilt-a)",
                    "EB0C": "$TC_CARR10[1] (c-tilt-b)", "EC0Y": None}),
    ("forkhead", {"EY0A": "$TC_CARR16[1] (a-y)", "EA0C": "$TC_CARR8[1] (c-tilt-a)",
                  "EC0A": "$TC_CARR11[1] (a-tilt-c)", "EB0Z": None}),
])
def test_reports_name_the_head_carrier_values(name: str, terms: dict[str, str | None]) -> None:
    """The report's controller term of a head link is the carrier value that holds it (a
    squareness link has none)."""
    from daemon.analysis.figures import controller_term

    _, spec = load_controller_kinematics(CFG / f"machines/{HEADS[name][0]}.yaml")
    for iso, want in terms.items():
        assert controller_term(iso, spec) == (None if want is None else f"Siemens {want}"), iso


def test_rumba_compensate_proposes_the_head_carrier_values(tmp_path: Path, capsys) -> None:
    """`rumba compensate` on an imported swivel-head run: the type M carrier's c-x takes EX0C,
    the head's b-x/b-z and c-y are skipped with the reason, and the reviewed MPF names them."""

    from contracts.probing_log import write_log
    from simulators.exact_log import shipped_run_rows
    from tests.cli_helpers import run_cli

    links = {"EX0C": -40, "EA0C": -19, "EB0C": 26, "EA0B": 22, "EC0B": -23, "EC0Y": 17,
             "EA0Z": -24, "EB0Z": -12}
    mpath = CFG / f"machines/{HEADS['swivelhead'][0]}.yaml"
    ppath = CFG / f"plans/{HEADS['swivelhead'][1]}.yaml"
    doc = {"store": {"path": str(tmp_path / "journal.sqlite")},
           "reports_dir": str(tmp_path / "reports"), "hmi": {"enabled": False},
           "machines": [{"name": "mill1", "machine": str(mpath), "artefact": str(ARTEFACT),
                         "plan": str(ppath), "dialect": "siemens",
                         "link": {"transport": "serial", "url": "/dev/ttyS0", "baudrate": 9600,
                                  "framing": "7E1"},
                         "tolerances": {"default_rotation_urad": {"warn": 100, "fail": 200},
                                        "default_translation_um": {"warn": 300, "fail": 500}}}]}
    cfg = tmp_path / "daemon.yaml"
    cfg.write_text(yaml.safe_dump(doc), encoding="utf-8")
    log = tmp_path / "run.csv"
    write_log(log, shipped_run_rows(mpath, ARTEFACT, ppath, links))
    code, _, err = run_cli(["history", "--config", str(cfg), "--import", str(log), "--machine",
                            "mill1"], capsys)
    assert code == 0, err
    code, out, err = run_cli(["compensate", "--config", str(cfg), "synth"], capsys)
    assert code == 0, out + err
    line = next(ln for ln in out.splitlines() if ln.strip().startswith("c-x"))
    assert "$TC_CARR15[1]" in line and "apply" in line
    delta_um = float(line.split("µm")[0].split()[-1])
    assert abs(delta_um + 40.0) < 3.0, line  # EX0C −40 µm: the C line's x by −40 µm
    for hidden in ("b-x", "b-z", "c-y"):
        assert any(ln.strip().startswith(hidden) and "skipped" in ln for ln in out.splitlines()), \
            (hidden, out)
    # listed as the program will write them (the proposal writes no program)
    assert re.search(r"\$TC_CARR15\[1\] = +-260\.04", out), out
    assert re.search(r"\$TC_CARR18\[1\] = +260\.04", out)  # l4 = −l3 keeps the chain closed
    code, out, err = run_cli(["compensate", "--config", str(cfg), "synth", "--confirm", "--by",
                              "eve"], capsys)
    assert code == 0, out + err
    program = Path(out.strip().splitlines()[-1].split("program: ")[1])
    text = program.read_text()
    assert program.suffix == ".mpf" and "$TC_CARR15[1]=-260.04" in text, text
    assert "$TC_CARR18[1]=260.04" in text
