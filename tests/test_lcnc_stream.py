"""LinuxCNC link and HAL probe logic that needs no LinuxCNC (runs in `make test`): the MDI step
plan and the AUTO program file of a real program, how an AUTO error names its touch, the probe's
contact geometry, the link config's guards, and our chain against the xyzbc-trt-kins formulas
(trtfuncs.c, tests/peers/PEERS_FINDINGS.md)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from contracts.setup_files import load_artefact, load_machine, load_plan
from contracts.yaml_files import ConfigError
from daemon.analysis import pipeline
from daemon.machines.setup import MachineSetup, TriggersFile
from daemon.machines.tolerances import Tolerances
from drivers.base import LinkError
from drivers.linuxcnc.program import auto_program, name_error, plan_steps
from drivers.registry import link_config
from identification.kinematics import ChainState, frames, to_model
from simulators.hal_probe import ProbeModel, write_spec
from simulators.truth import TruthModel

ROOT = Path(__file__).resolve().parents[1]
MACHINE = ROOT / "config/machines/linuxcnc_xyzbc.yaml"
ARTEFACT = ROOT / "config/artefacts/thesis_4ball.yaml"
ERRORS = ROOT / "config/errors/linuxcnc_xyzbc.yaml"


def _program() -> pipeline.Prepared:
    m, mf = load_machine(MACHINE)
    plan = load_plan(ROOT / "config/plans/linuxcnc_4poses.yaml")
    setup = MachineSetup("t", m, mf, load_artefact(ARTEFACT), plan, "linuxcnc", None,
                         TriggersFile(), Tolerances(), 60.0, (), False)
    return pipeline.prepare(setup, "r1")


def test_mdi_steps_of_a_real_program() -> None:
    prep = _program()
    text = prep.job.text
    steps = plan_steps(text)
    sent = [s.text for s in steps if s.kind == "mdi"]
    assert not any(s.startswith(("(", "%", "o")) or s == "M2" for s in sent)
    assert all(len(s.prefix + s.text) < 240 for s in steps)
    # every motion block of the program is sent, once, in order
    moves = [ln for ln in text.splitlines() if re.match(r"^N\d+ G", ln)]
    assert [s for s in sent if s.startswith("N")] == moves
    results = [s for s in steps if s.kind == "result"]
    assert len(results) == prep.job.touch_count
    for k, r in enumerate(results, 1):
        f = r.text.split()
        assert f[:2] == ["RUMBA", str(k)] and f[6:] == ["#5070", "#5061", "#5062", "#5063",
                                                         "#5065", "#5066"]
        assert r.prefix.endswith(f"#3999={k}")  # the slot assignments ride along
    probes = [s for s in steps if "G38.2" in s.text]
    assert len(probes) == len(results)
    for p, r in zip(probes, results, strict=True):
        f = r.text.split()
        assert p.touch == f"touch seq {f[1]} pose {f[3]} ball {f[4]} touch {f[5]}"


def test_auto_program_keeps_lines_and_sends_results_through_debug() -> None:
    prep = _program()
    text = prep.job.text
    src, out = text.split("\n"), auto_program(text).split("\n")
    assert out[-1] == "" and len(out) - 1 == len(src) - (src[-1] == "")  # LinuxCNC line = ours
    debug = [ln for ln in out if ln.startswith("(DEBUG,")]
    assert len(debug) == prep.job.touch_count
    assert debug[0] == "(DEBUG,RUMBA 1 0 0 B1 1 #5070 #5061 #5062 #5063 #5065 #5066)"
    assert not any(ln.upper().startswith("(LOG") for ln in out)  # no log file on the PC
    for a, b in zip(src, out, strict=False):
        if not a.upper().startswith("(LOG"):
            assert a.strip() == b  # motion, probing, miss check and M2 untouched
    assert sum("G38.2" in ln for ln in out) == prep.job.touch_count
    with pytest.raises(LinkError, match="program line 2"):
        auto_program("%\nG0 X1 (caf\u00e9)\n%")


def test_auto_error_names_the_touch_and_the_line() -> None:
    text = _program().job.text
    steps, lines = plan_steps(text), text.split("\n")
    probes = [st for st in steps if st.touch]
    g38 = probes[1].line  # the second probing block: seq 2
    msg = name_error([f"{g38} G38.2 move finished without making contact."], 1, probes, lines)
    assert msg.startswith("G38.2 move finished without making contact. at "
                          f"program line {g38} 'N12 G38.2 ")
    assert msg.endswith("(touch seq 2 pose 0 ball B1 touch 2)")
    # a probe error reported on another line: the touch after the last result
    msg = name_error(["3 Probe tripped during non-probe move."], 4, probes, lines)
    assert "touch seq 5 " in msg
    # any other error: the program line LinuxCNC stopped at
    line = next(st.line for st in steps if st.text.startswith("N9 "))
    msg = name_error([f"{line} Joint 0 following error", f"{line} Spindle stopped"], 2, probes,
                     lines)
    assert msg == (f"Joint 0 following error; Spindle stopped at program line {line} "
                   "'N9 G0 X-82.8000' (after touch 2)")


def test_probe_servo_terms_give_the_sphere_distance(tmp_path: Path) -> None:
    truth = TruthModel.from_files(MACHINE, ARTEFACT, ERRORS)
    spec = write_spec(truth, tmp_path / "s.json")
    spec["touch_noise_mm"] = 0.0
    model = ProbeModel(spec)
    b, c, ball = 30.0, 60.0, 2
    centre = truth.centre_ctrl(ball, b, c)  # controller X Y Z of the true centre
    # approach along a diagonal, missing the true centre by 0.2 mm laterally
    d = np.array([1.0, 1.0, 0.0]) / np.sqrt(2)
    line0 = centre - 20.0 * d + np.array([0.1, -0.1, 0.05])
    s = np.linspace(0.0, 8.0, 4001)
    gaps = np.array([model.gap_mm(*(line0 + si * d), b, c) for si in s])
    k = int(np.argmax(gaps <= 0))
    assert k > 0 and gaps[k - 1] > 0  # the stylus meets the ball on this line
    # what the servo thread computes from the published terms: |U·q − m_i| against r_i
    pins = dict(model.servo_pins(b, c))
    u = np.zeros((3, 3))
    for p in ("u00", "u01", "u02", "u11", "u12", "u22"):
        u[int(p[1]), int(p[2])] = pins[p]
    m = np.array([pins[f"ball-{ball}-{a}"] for a in "xyz"])
    servo = np.array([np.linalg.norm(u @ (line0 + si * d) - m) for si in s]) \
        - pins[f"ball-{ball}-r"]
    assert np.abs(servo - gaps).max() < 1e-9  # the sphere itself, along any line (mm)
    assert pins["b-min"] < b < pins["b-max"] and pins["c-min"] < c < pins["c-max"]
    model.present[:] = False
    assert model.gap_mm(*(line0 + s[k] * d), b, c) > 1e6  # every ball removed: nothing to touch
    assert all(v < 0 for p, v in model.radius_pins())  # and nothing the servo thread can touch


def test_link_config_refuses_injection_and_unknown_keys() -> None:
    ok = link_config({"transport": "linuxcnc", "port": 5007, "prelude_mdi": ["M429"]})
    assert ok.mode == "remote" and ok.host == "127.0.0.1" and ok.run == "mdi"
    local = link_config({"transport": "linuxcnc", "mode": "local"})
    assert local.run == "mdi"  # AUTO is opt-in (LinuxCNC's probe race, config/linuxcnc/)
    assert link_config({"transport": "linuxcnc", "mode": "local", "run": "auto"}).run \
        == "auto"
    with pytest.raises(ConfigError, match="needs mode: local"):
        link_config({"transport": "linuxcnc", "run": "auto"})  # no upload through linuxcncrsh
    with pytest.raises(ConfigError, match="program_dir"):  # a line break would reach the helper
        link_config({"transport": "linuxcnc", "mode": "local", "program_dir": "/tmp/a\nM2"})
    with pytest.raises(ConfigError, match="program_dir"):
        link_config({"transport": "linuxcnc", "mode": "local", "program_dir": "relative/dir"})
    with pytest.raises(ConfigError, match="prelude_mdi"):
        link_config({"transport": "linuxcnc", "prelude_mdi": ["M429 (DEBUG,x)"]})
    with pytest.raises(ConfigError, match="prelude_mdi"):
        link_config({"transport": "linuxcnc", "prelude_mdi": ["M429\nM2"]})
    with pytest.raises(ConfigError, match="unknown key"):
        link_config({"transport": "linuxcnc", "prot": 5007})


def test_chain_matches_trtfuncs_formulas() -> None:
    """The forward formula of xyzbc-trt-kins with the HAL pins of config/linuxcnc/ (R = 0,
    O = (12.5, 0, -40)): P = Rz(-c)·(Ry(-b)·(J - R - O) + O) + R."""
    machine, _ = load_machine(MACHINE)
    rng = np.random.default_rng(5)
    j = np.column_stack([rng.uniform(-300, 300, (200, 3)), rng.uniform(-120, 120, 200),
                         rng.uniform(-720, 720, 200)])
    qm = to_model(machine, {k: j[:, i] for i, k in enumerate("XYZBC")})
    f_w, f_t = frames(machine, qm, ChainState())
    ours = np.einsum("sji,sj->si", f_w[:, :3, :3], f_t[:, :3, 3] - f_w[:, :3, 3])

    def ry(t: float) -> np.ndarray:
        c, s = np.cos(t), np.sin(t)
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])

    def rz(t: float) -> np.ndarray:
        c, s = np.cos(t), np.sin(t)
        return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])

    o = np.array([12.5, 0.0, -40.0])
    for row, p in zip(j, ours, strict=True):
        b, c = np.radians(row[3]), np.radians(row[4])
        want = rz(-c) @ (ry(-b) @ (row[:3] - o) + o)
        assert np.allclose(p, want, atol=1e-9)
