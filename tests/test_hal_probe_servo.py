"""The LinuxCNC HAL probe's servo-thread trip without LinuxCNC (runs in `make test`): the HAL
file simulators/linuxcnc_files.py writes, evaluated component by component in its addf order as
LinuxCNC's servo thread would, fed by simulators/hal_probe.py's published terms. The userspace
half is starved on purpose (it publishes once per indexation and never during a probing move):
the trip must still be the truth model's contact to the servo sample, for any approach
direction; a half-written or stale set must never trip (signal rumba-probe-hold says so); only a
collision trips outside probing moves."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from simulators.hal_probe import CRASH_MM, ProbeModel, snapshot, write_spec
from simulators.linuxcnc_files import write_probe_hal
from simulators.truth import TruthModel

ROOT = Path(__file__).resolve().parents[1]
MACHINE = ROOT / "config/machines/linuxcnc_xyzbc.yaml"
ARTEFACT = ROOT / "config/artefacts/thesis_4ball.yaml"
ERRORS = ROOT / "config/errors/linuxcnc_xyzbc.yaml"
PROBING, RAPID = 5, 1  # motion.motion-type
STEP_MM = 5.0 * 0.25e-3  # F300 over one 0.25 ms servo period


class ServoThread:
    """The realtime half of a HAL file: loadrt/addf/net/setp of the stock components it uses."""

    FUNCS = {
        "mult2": lambda p: {"out": p("in0") * p("in1")},
        "sum2": lambda p: {"out": p("in0") * p("gain0", 1.0) + p("in1") * p("gain1", 1.0)
                           + p("offset")},
        "hypot": lambda p: {"out": math.sqrt(p("in0") ** 2 + p("in1") ** 2 + p("in2") ** 2)},
        "comp": lambda p: {"out": p("in1") > p("in0")},
        "or2": lambda p: {"out": bool(p("in0")) or bool(p("in1"))},
        "and2": lambda p: {"out": bool(p("in0")) and bool(p("in1"))},
        "not": lambda p: {"out": not p("in")},
        "wcomp": lambda p: {"out": p("min") < p("in") < p("max")},
        "conv_s32_float": lambda p: {"out": float(p("in"))},
    }

    def __init__(self, text: str) -> None:
        self.kind: dict[str, str] = {}
        self.order: list[str] = []
        self.sig_of: dict[str, str] = {}
        self.signals: dict[str, float] = {}
        self.values: dict[str, float] = {}
        for line in text.splitlines():
            f = line.split()
            if f[0] == "loadrt":
                for name in f[2].removeprefix("names=").split(","):
                    assert name not in self.kind, name
                    self.kind[name] = f[1]
            elif f[0] == "addf":
                self.order.append(f[1])
            elif f[0] == "setp":
                self.values[f[1]] = float(f[2])
            elif f[0] == "net":
                for pin in (t for t in f[2:] if t != "=>"):
                    assert pin not in self.sig_of, f"{pin} on two signals"
                    self.sig_of[pin] = f[1]
        assert sorted(self.order) == sorted(self.kind), "every component in the servo thread"

    def get(self, pin: str, default: float = 0.0) -> float:
        if pin in self.sig_of:
            return self.signals.get(self.sig_of[pin], default)
        return self.values.get(pin, default)

    def set(self, pin: str, value: float) -> None:
        """An outside writer: joint.N.pos-fb, motion.motion-type, rumba-probe.*."""
        self.values[pin] = value
        if pin in self.sig_of:
            self.signals[self.sig_of[pin]] = value

    def period(self) -> None:
        for name in self.order:
            out = self.FUNCS[self.kind[name]](lambda p, d=0.0, n=name: self.get(f"{n}.{p}", d))
            for p, v in out.items():
                self.set(f"{name}.{p}", v)


@pytest.fixture(scope="module")
def model_spec(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, Path]:
    truth = TruthModel.from_files(MACHINE, ARTEFACT, ERRORS)
    spec_path = tmp_path_factory.mktemp("probe") / "probe_spec.json"
    return write_spec(truth, spec_path), spec_path


def _servo(spec_path: Path, tmp: Path) -> ServoThread:
    write_probe_hal(tmp / "probe.hal", spec_path)
    return ServoThread((tmp / "probe.hal").read_text().split("\n", 1)[1])  # minus loadusr


def _at(st: ServoThread, q: np.ndarray, motion: int) -> tuple[bool, bool]:
    for i, v in enumerate(q):
        st.set(f"joint.{i}.pos-fb", float(v))
    st.set("motion.motion-type", motion)
    st.period()
    return bool(st.get("motion.probe-input")), bool(st.get("rumba-hold.out"))


def _publish(st: ServoThread, pins: list[tuple[str, float]]) -> None:
    for p, v in pins:
        st.set(f"rumba-probe.{p}", v)


def _joints_of(model: ProbeModel, tip_w: np.ndarray, b: float, c: float) -> np.ndarray:
    """Joint X Y Z B C that put the true tip at ``tip_w`` (workpiece frame) at this B C."""
    model.nearest(0.0, 0.0, 0.0, b, c)
    return np.r_[np.linalg.solve(model._a, tip_w - model._t), b, c]


@pytest.mark.parametrize("b,c", [(0.0, 0.0), (-30.0, 45.0), (20.0, -120.0)])
def test_a_starved_userspace_half_still_trips_at_the_contact_from_any_direction(
        model_spec, tmp_path, b, c) -> None:
    spec, spec_path = model_spec
    model = ProbeModel(spec)
    st = _servo(spec_path, tmp_path)
    _publish(st, model.servo_pins(b, c))  # once, at rest, before the moves: never again
    rng = np.random.default_rng(3)
    for k in range(len(model.centres)):
        centre = model.centres[k] + model._visit[k]
        contact = model.contact_mm[k] + model._n
        for _ in range(3):
            # a line through the sphere off its centre by up to 0.6 of the radius: not radial,
            # so a plane at the tip's projection would be wrong here; the sphere is not
            n = rng.normal(size=3)
            n /= np.linalg.norm(n)
            side = np.cross(n, rng.normal(size=3))
            side *= rng.uniform(0, 0.6) * contact / np.linalg.norm(side)
            depth = math.sqrt(contact**2 - side @ side)
            start = centre + side + n * (depth + 0.2 + 0.37 * STEP_MM)  # off the grid
            tripped = None
            for s in range(400):  # 0.5 mm at F300, one servo period a step
                q = _joints_of(model, start - n * s * STEP_MM, b, c)
                hit, hold = _at(st, q, PROBING)
                assert not hold, "the set of this indexation is up: no hold"
                inside = model.gap_mm(*q) <= 0.0
                assert hit == inside, (k, s, model.gap_mm(*q))
                if hit and tripped is None:
                    tripped = s
            assert tripped == 161, tripped  # the first servo sample past the sphere


def test_a_half_written_or_stale_set_never_trips_and_holds_the_probing_move(model_spec,
                                                                             tmp_path) -> None:
    spec, spec_path = model_spec
    model = ProbeModel(spec)
    st = _servo(spec_path, tmp_path)
    _publish(st, model.servo_pins(0.0, 0.0))
    # the machine indexed to B-30 C45; the tip 5 um inside ball 0 there, and where the stale
    # B0 C0 set puts it: outside that ball (a stale set would miss) or deep inside another
    b, c = -30.0, 45.0
    new = model.servo_pins(b, c)
    centre = model.centres[0] + model._visit[0]
    tip = centre + np.array([0.0, 0.0, model.contact_mm[0] + model._n - 0.005])
    q = _joints_of(model, tip, b, c)
    assert -0.006 < model.gap_mm(*q) < 0
    for k in range(len(new)):
        _publish(st, new[:k])  # the component preempted after k writes
        for motion in (PROBING, RAPID):
            hit, hold = _at(st, q, motion)
            assert not hit, f"a trip on a set written {k}/{len(new)} pins far"
            assert hold == (motion == PROBING), k
        _publish(st, model.servo_pins(0.0, 0.0))  # back to the stale, complete set
        assert _at(st, q, PROBING) == (False, True)
    _publish(st, new)
    assert _at(st, q, PROBING) == (True, False)
    assert _at(st, q, RAPID) == (False, False)  # touching outside a probing move: no edge


def test_outside_probing_moves_only_a_collision_trips(model_spec, tmp_path) -> None:
    spec, spec_path = model_spec
    model = ProbeModel(spec)
    st = _servo(spec_path, tmp_path)
    _publish(st, model.servo_pins(0.0, 0.0))
    centre = model.centres[2] + model._visit[2]
    r = model.contact_mm[2] + model._n
    for depth, crash in ((0.05, False), (CRASH_MM + 0.01, True)):
        q = _joints_of(model, centre + np.array([r - depth, 0.0, 0.0]), 0.0, 0.0)
        assert _at(st, q, RAPID) == (crash, False), depth
        assert _at(st, q, PROBING) == (True, False)
    # a ball taken off the table (ball-K-present 0) is never touched, however deep
    model.present[2] = False
    _publish(st, model.radius_pins())
    assert _at(st, q, PROBING) == (False, False) and _at(st, q, RAPID) == (False, False)


def test_a_snapshot_is_one_servo_sample_not_a_torn_read() -> None:
    # the servo thread moves every joint by 1 between reads 3 and 4 of the first pass
    reads = {"n": 0}

    def read(j: str) -> float:
        reads["n"] += 1
        return 10.0 * "xyzbc".index(j) + (reads["n"] > 3)

    q = snapshot(read)
    assert q == (1.0, 11.0, 21.0, 31.0, 41.0)
