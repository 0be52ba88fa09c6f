"""HAL userspace half of the LinuxCNC sim probe: the terms on which the servo thread trips
``motion.probe-input``, from our simulator's truth model (balls + setup errors, link errors,
stylus tip, noise).

Two halves in one file:

* ``write_spec(truth, path)`` runs in the daemon's venv: it flattens a ``simulators.truth``
  ``TruthModel`` into JSON (chain, link errors in model units, true ball centres, radii, noise).
* ``main()`` is the HAL component, run by LinuxCNC with Debian's ``/usr/bin/python3`` (the only
  interpreter with the ``hal`` module; it has numpy but not scipy/pydantic, so it imports
  ``identification.kinematics`` only)::

      loadusr -Wn rumba-probe /usr/bin/python3 simulators/hal_probe.py SPEC.json

  Pins: ``rumba-probe.x y z b c`` (float in, netted from ``joint.N.pos-fb``); the servo-thread
  terms (float out, below): ``u00 u01 u02 u11 u12 u22``, ``ball-K-x y z r crash-r``, ``b-min
  b-max c-min c-max``; diagnostics of the userspace view: ``out`` (bit out, the tip touches a
  ball), ``contacts`` (s32 out, rising edges of ``out``), ``gap-um`` (float out, smallest signed
  stylus-to-ball gap), ``crash`` (bit out, the stylus > 0.1 mm inside a ball in a consistent
  joint snapshot: trips LinuxCNC in any move); ``temp-x y z`` (float out, °C: the errors file's
  thermal sensors warming from the component's start). Parameters: ``ball-K-present``
  (bit rw, K = artefact order, all 1 at start; ``halcmd setp rumba-probe.ball-1-present 0``
  removes ball 1 from the table).

Contact (METHOD.md §1-2, thesis Eq. 3.1): the stylus sphere touches ball i when
``|tip_w − c_i| <= R_i + r − pretravel + n`` with ``tip_w`` the true tip centre in the last
workpiece frame (affine in X Y Z at fixed B C, so one 3x3 product per poll), ``c_i`` the true
centre (nominal + setup error + a per-visit centre noise redrawn at every new indexation) and
``n`` a per-touch noise along the normal, redrawn when the probe re-arms.

The trip is decided in the servo thread, never by this process (simulators/linuxcnc_files.py):
at a fixed B C, ``tip_w = A·q + t`` with ``A = Q·U`` (QR, U upper triangular), so
``|tip_w − c_i| = |U·q − m_i|`` with ``m_i = Qᵀ(c_i − t)``: the component publishes U and every
``m_i`` once per indexation, and stock realtime components (mult2, sum2, hypot, comp) compare
``|U·q − m_i|`` with the contact radius ``R_i + r − pretravel + n`` at every servo period — exact
for any approach direction, whatever the scheduler does to this process. The terms hold for
the B C they were computed at: the component publishes them behind a window on B and C
(``wcomp``; invalidated first, data, window last), so a half-written or stale set is never used
(signal ``rumba-probe-hold``: a probing move running without its set; the poll follows an
indexation within ~1 ms, long before the approach ends).

Servo-period overshoot: LinuxCNC latches the first servo sample at which it sees the input high,
so the latched point lies past the contact by ``v·T·u`` (u uniform in 0..1, T the servo period)
plus a constant one-sample delay. Its mean is a constant radial pre-travel, absorbed by the
free-radius sphere fit; its spread ``v·T/√12`` adds to the touch noise
(config/linuxcnc/README.md).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
JOINTS = ("x", "y", "z", "b", "c")
U_PINS = ("u00", "u01", "u02", "u11", "u12", "u22")  # U·q in the servo thread (QR of A)
POLL_S = 1e-3  # the trip is the servo thread's: the poll only follows indexations and noise
WINDOW_DEG = 1e-6  # the terms hold within this of the B C they were computed at (9 nm at 500 mm)
INVALID = -1e9  # b-max while the terms are rewritten: the B window is empty, no trip, no crash
REARM_MM = 0.5  # farther than this from every ball the probe is re-armed: new touch noise
NEVER = -1.0  # contact radius of an absent ball: |U·q − m| is never below it
CRASH_MM = 0.1  # the stylus this deep inside a ball is a collision, whatever the move


def write_spec(truth: Any, path: Path | str, absent: tuple[str, ...] = ()) -> dict:
    """Write the JSON the component reads (venv side). ``absent``: ball ids not on the table."""
    import numpy as np

    m = truth.machine
    probe = truth.errors.probe
    ids = list(truth.artefact.ids)
    unknown = [b for b in absent if b not in ids]
    if unknown:
        raise ValueError(f"absent balls {unknown} not in artefact {ids}")
    if truth.has_motion_errors:
        # The servo thread tests contact with ONE affine map per indexation (module
        # docstring); position-dependent motion errors bend it by µm across the balls.
        raise ValueError("the HAL probe carries link and setup errors only, not motion errors "
                         "(effects, motion_errors): remove them from the errors file, or run "
                         "the map on the virtual controller (rumba sim)")
    spec = {
        "machine": {
            "name": m.name, "topology": m.topology, "tool_tip_mm": list(m.tool_tip_mm),
            "spindle_axis": list(m.spindle_axis),
            "axes": {k: {"kind": a.kind, "direction": list(a.direction),
                         "point_mm": list(a.point_mm), "sign": a.sign}
                     for k, a in m.axes.items()},
        },
        "rotary": list(m.rotary_axes),
        "links": {k: float(v) for k, v in truth.links.items()},
        "tip_offset_mm": np.asarray(truth.tip_setup_mm, float).tolist(),
        "ball_ids": ids,
        "ball_centres_mm": (truth.artefact.nominal_mm + truth.ball_setup_mm).tolist(),
        "ball_radii_mm": truth.ball_radii_mm.tolist(),
        "stylus_radius_mm": float(truth.stylus_radius_mm),
        "pretravel_mm": probe.pretravel_um * 1e-3,
        "touch_noise_mm": probe.touch_noise_um * 1e-3,
        "centre_noise_mm": [v * 1e-3 for v in probe.centre_noise_um],
        "absent": sorted({ids.index(b) for b in absent} | set(truth.absent)),
        "seed": int(truth.seed),
        "thermal": _thermal(truth),
    }
    Path(path).write_text(json.dumps(spec, indent=1), encoding="utf-8")
    return spec


def _thermal(truth: Any) -> dict:
    """The structure sensors' warm-up (simulators/thermal.py) for the ``temp-x y z`` pins."""
    th = truth.thermal
    if th is None:
        return {"ambient_c": 20.0, "start_state": 0.0, "axes": {}}
    return {"ambient_c": th.ambient_c, "start_state": th.start_state,
            "axes": {a: [w.rise_c, w.tau_s] for a, w in th.axes.items()}}


def sensor_c(thermal: dict, axis: str, t_s: float) -> float:
    """What the structure sensor on ``axis`` reads ``t_s`` after the component started (the
    thermal state of simulators/thermal.py, warming from LinuxCNC's start: no drift here)."""
    import math

    rise, tau = thermal["axes"].get(axis.upper(), [0.0, 1.0])
    s = 1.0 - (1.0 - thermal["start_state"]) * math.exp(-max(t_s, 0.0) / tau)
    return thermal["ambient_c"] + rise * s


class ProbeModel:
    """The contact test of the component, separate from HAL so it can be checked anywhere."""

    def __init__(self, spec: dict) -> None:
        import numpy as np

        from identification.kinematics import Axis, ChainState, Machine

        ms = spec["machine"]
        axes = {k: Axis(k, a["kind"], tuple(a["direction"]), tuple(a["point_mm"]),
                        sign=int(a["sign"])) for k, a in ms["axes"].items()}
        self.machine = Machine(ms["name"], ms["topology"], axes, tuple(ms["tool_tip_mm"]),
                               tuple(ms["spindle_axis"]))
        self.rotary = tuple(spec["rotary"])
        self.state = ChainState(links=dict(spec["links"]),
                                tip_offset_mm=np.asarray(spec["tip_offset_mm"], float))
        self.centres = np.asarray(spec["ball_centres_mm"], float)
        self.contact_mm = (np.asarray(spec["ball_radii_mm"], float) + spec["stylus_radius_mm"]
                           - spec["pretravel_mm"])
        self.present = np.ones(len(self.centres), bool)
        self.present[list(spec["absent"])] = False
        self.touch_noise = float(spec["touch_noise_mm"])
        self.centre_noise = np.asarray(spec["centre_noise_mm"], float)
        self.rng = np.random.default_rng(int(spec["seed"]))
        self._key: tuple[float, float] | None = None
        self._a = np.eye(3)
        self._t = np.zeros(3)
        self._visit = np.zeros_like(self.centres)
        self._n = 0.0
        self.redraw_touch()

    def _affine(self, b: float, c: float) -> None:
        """tip_w = A @ [X Y Z] + t at this indexation (exact without motion errors)."""
        import numpy as np

        from identification.kinematics import frames, to_model

        q = np.zeros((4, 5))
        q[1:, :3] = np.eye(3)
        q[:, 3], q[:, 4] = b, c
        r1, r2 = self.rotary
        qm = to_model(self.machine, {"X": q[:, 0], "Y": q[:, 1], "Z": q[:, 2],
                                     r1: q[:, 3], r2: q[:, 4]})
        f_w, f_t = frames(self.machine, qm, self.state)
        tip = np.asarray(self.machine.tool_tip_mm, float) + self.state.tip_offset_mm
        tip_f = f_t[:, :3, :3] @ tip + f_t[:, :3, 3]
        tip_w = np.einsum("sji,sj->si", f_w[:, :3, :3], tip_f - f_w[:, :3, 3])
        self._a, self._t = (tip_w[1:] - tip_w[0]).T, tip_w[0]

    def redraw_touch(self) -> None:
        self._n = float(self.rng.normal(0.0, self.touch_noise)) if self.touch_noise else 0.0

    def gap_mm(self, x: float, y: float, z: float, b: float, c: float) -> float:
        """Smallest signed gap (mm) between the stylus sphere and a present ball sphere."""
        return self.nearest(x, y, z, b, c)[0]

    def servo_pins(self, b: float, c: float) -> list[tuple[str, float]]:
        """The servo thread's terms at this indexation, in write order: the B window emptied
        first, U and the ball centres ``m_i``, the contact radii, the window last — the servo
        thread never uses a half-written or stale set (module docstring)."""
        import numpy as np

        self.nearest(0.0, 0.0, 0.0, b, c)  # the affine (and the visit noise) of this B C
        q, u = np.linalg.qr(self._a)
        d = np.where(np.diag(u) < 0, -1.0, 1.0)
        q, u = q * d, d[:, None] * u  # A = Q·U with a positive diagonal: U ≈ I
        m = (self.centres + self._visit - self._t) @ q  # rows m_i = Qᵀ(c_i − t)
        pins: list[tuple[str, float]] = [("b-max", INVALID)]
        pins += [(p, float(u[int(p[1]), int(p[2])])) for p in U_PINS]
        for k, mk in enumerate(m):
            pins += [(f"ball-{k}-{a}", float(v)) for a, v in zip("xyz", mk, strict=True)]
        pins += self.radius_pins()
        return [*pins, ("c-min", c - WINDOW_DEG), ("c-max", c + WINDOW_DEG),
                ("b-min", b - WINDOW_DEG), ("b-max", b + WINDOW_DEG)]

    def radius_pins(self) -> list[tuple[str, float]]:
        """``ball-K-r`` (contact: ``R_i + r − pretravel + n``) and ``ball-K-crash-r`` (that less
        CRASH_MM) of every ball; NEVER for a ball not on the table."""
        out: list[tuple[str, float]] = []
        for k, r in enumerate(self.contact_mm + self._n):
            ok = bool(self.present[k])
            out += [(f"ball-{k}-r", float(r) if ok else NEVER),
                    (f"ball-{k}-crash-r", float(r) - CRASH_MM if ok else NEVER)]
        return out

    def nearest(self, x: float, y: float, z: float, b: float, c: float
                ) -> tuple[float, int, object]:
        """(gap mm, ball index or -1, tip in the workpiece frame) of the nearest present ball."""
        import numpy as np

        key = (round(b, 9), round(c, 9))
        if key != self._key:
            if self._key is None or max(abs(key[0] - self._key[0]),
                                        abs(key[1] - self._key[1])) > 1e-6:
                self._visit = self.rng.normal(0.0, 1.0, self.centres.shape) * self.centre_noise
            self._affine(b, c)
            self._key = key
        tip = self._a @ np.array([x, y, z]) + self._t
        if not self.present.any():
            return 1e9, -1, tip
        idx = np.flatnonzero(self.present)
        d = np.linalg.norm(self.centres[idx] + self._visit[idx] - tip, axis=1)
        g = d - self.contact_mm[idx] - self._n
        k = int(np.argmin(g))
        return float(g[k]), int(idx[k]), tip


def snapshot(read: Any, tries: int = 5) -> tuple[float, ...]:
    """The five joints read twice until both reads agree: one servo sample, not X of one period
    and C of a later one (a torn read mid-rapid can put the tip inside a ball)."""
    q = tuple(read(j) for j in JOINTS)
    for _ in range(tries):
        again = tuple(read(j) for j in JOINTS)
        if again == q:
            break
        q = again
    return q


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1:
        print("usage: hal_probe.py SPEC.json", file=sys.stderr)
        return 2
    sys.path.insert(0, str(REPO))
    import hal  # Debian's /usr/bin/python3 only

    spec = json.loads(Path(argv[0]).read_text(encoding="utf-8"))
    model = ProbeModel(spec)
    comp = hal.component("rumba-probe")
    for j in JOINTS:
        comp.newpin(j, hal.HAL_FLOAT, hal.HAL_IN)
    comp.newpin("out", hal.HAL_BIT, hal.HAL_OUT)
    comp.newpin("contacts", hal.HAL_S32, hal.HAL_OUT)
    comp.newpin("gap-um", hal.HAL_FLOAT, hal.HAL_OUT)
    comp.newpin("crash", hal.HAL_BIT, hal.HAL_OUT)  # trips LinuxCNC in any move (peer HAL)
    n = len(model.centres)
    names = [p for p, _ in model.servo_pins(0.0, 0.0)]
    for p in dict.fromkeys(names):
        comp.newpin(p, hal.HAL_FLOAT, hal.HAL_OUT)
    comp["b-min"], comp["b-max"] = 1.0, INVALID  # an empty window until the first set is up
    thermal = spec.get("thermal") or {"ambient_c": 20.0, "start_state": 0.0, "axes": {}}
    for a in "xyz":  # structure temperatures: what a shop wires to its sensors
        comp.newpin(f"temp-{a}", hal.HAL_FLOAT, hal.HAL_OUT)
    for k in range(n):
        comp.newparam(f"ball-{k}-present", hal.HAL_BIT, hal.HAL_RW)
        comp[f"ball-{k}-present"] = bool(model.present[k])
    comp.ready()
    out, contacts, published = False, 0, None
    t_ready = time.monotonic()
    try:
        while True:
            present = [bool(comp[f"ball-{k}-present"]) for k in range(n)]
            q = snapshot(lambda j: comp[j])
            now = time.monotonic()
            for a in "xyz":
                comp[f"temp-{a}"] = sensor_c(thermal, a, now - t_ready)
            key = (round(q[3], 9), round(q[4], 9))
            if key != published:  # a new indexation: the servo thread's terms for it
                model.present[:] = present
                for p, v in model.servo_pins(q[3], q[4]):
                    comp[p] = v
                published = key
            gap = model.gap_mm(*q)
            redraw = gap > REARM_MM and not out  # away from every ball: the probe re-arms
            if redraw or present != list(model.present):
                model.present[:] = present
                if redraw:
                    model.redraw_touch()
                for p, v in model.radius_pins():  # one pin each: old or new, never torn
                    comp[p] = v
            hit = gap <= 0.0
            if hit and not out:
                contacts += 1
                comp["contacts"] = contacts
            out = hit
            comp["out"] = out
            comp["gap-um"] = gap * 1e3
            comp["crash"] = gap < -CRASH_MM
            time.sleep(POLL_S)
    except KeyboardInterrupt:
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
