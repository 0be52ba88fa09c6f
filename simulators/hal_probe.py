"""HAL userspace probe for LinuxCNC: drives ``motion.probe-input`` from the joint feedback through
our simulator's truth model (balls + setup errors, link errors, stylus tip, noise).

Two halves in one file:

* ``write_spec(truth, path)`` runs in the daemon's venv: it flattens a ``simulators.truth``
  ``TruthModel`` into JSON (chain, link errors in model units, true ball centres, radii, noise).
* ``main()`` is the HAL component, run by LinuxCNC with Debian's ``/usr/bin/python3`` (the only
  interpreter with the ``hal`` module; it has numpy but not scipy/pydantic, so it imports
  ``identification.kinematics`` only)::

      loadusr -Wn rumba-probe /usr/bin/python3 simulators/hal_probe.py SPEC.json

  Pins: ``rumba-probe.x y z b c`` (float in, netted from ``joint.N.pos-fb``), ``out`` (bit out →
  ``motion.probe-input`` while probing), ``crash`` (bit out, stylus > 0.1 mm inside a ball: trips
  in any move), ``contacts`` (s32 out, rising edges), ``gap-um`` (float out, smallest
  signed stylus-to-ball gap), ``temp-x y z`` (float out, °C: the errors file's thermal
  sensors warming from the component's start, issue 22). Parameters: ``ball-K-present`` (bit
  rw, K = artefact order, all 1 at start; ``halcmd setp rumba-probe.ball-1-present 0``
  removes ball 1 from the table).

Contact (METHOD.md §1-2, thesis Eq. 3.1): the stylus sphere touches ball i when
``|tip_w − c_i| <= R_i + r − pretravel + n`` with ``tip_w`` the true tip centre in the last
workpiece frame (affine in X Y Z at fixed B C, so one 3x3 product per poll), ``c_i`` the true
centre (nominal + setup error + a per-visit centre noise redrawn at every new indexation) and
``n`` a per-touch noise along the normal, redrawn when the probe re-arms.

Servo-period overshoot: LinuxCNC latches the first servo sample at which it sees the input high,
so the latched point lies past the contact by ``v·T·u`` (u uniform in 0..1, T the servo period;
the poll sleeps in proportion to the gap and spins within 0.05 mm, while the axes move, so the
input rises within tens of µs of the sample that crosses).
Its mean is a constant radial pre-travel, absorbed by the free-radius sphere fit; its spread
``v·T/√12`` adds to the touch noise (config/linuxcnc/README.md).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
JOINTS = ("x", "y", "z", "b", "c")
PLANE_PINS = ("plane-wx", "plane-wy", "plane-wz", "plane-k")
MAX_POLL_S = 2e-3
ARM_GAP_MM = 0.5  # the servo-thread tangent plane is armed this close to a ball
BUSY_GAP_MM = 0.05  # closer than this the poll spins (no sleep): the input rises within ~30 us
MAX_SPEED_MM_S = 600.0  # above the sim machines' 500 mm/s: the poll never sleeps past a contact
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
        raise ValueError("the HAL probe carries link and setup errors only, not motion errors "
                         "(effects): remove 'effects' from the errors file")
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

    def plane(self, x: float, y: float, z: float, b: float, c: float
              ) -> tuple[float, float, float, float] | None:
        """(wx, wy, wz, k) with ``wx·X + wy·Y + wz·Z + k`` = the signed distance of the tip to
        the tangent plane of the nearest ball at the tip's radial projection, when that ball
        is closer than ``ARM_GAP_MM`` (else None). The servo thread trips on it (see main)."""
        import numpy as np

        gap, i, tip = self.nearest(x, y, z, b, c)
        if i < 0 or gap > ARM_GAP_MM:
            return None
        centre = self.centres[i] + self._visit[i]
        n = tip - centre
        n /= np.linalg.norm(n)
        contact = centre + (self.contact_mm[i] + self._n) * n
        w = self._a.T @ n
        return float(w[0]), float(w[1]), float(w[2]), float(n @ (self._t - contact))

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
    for p in PLANE_PINS:
        comp.newpin(p, hal.HAL_FLOAT, hal.HAL_OUT)
    comp["plane-k"] = 1e6
    thermal = spec.get("thermal") or {"ambient_c": 20.0, "start_state": 0.0, "axes": {}}
    for a in "xyz":  # structure temperatures (issue 22): what a shop wires to its sensors
        comp.newpin(f"temp-{a}", hal.HAL_FLOAT, hal.HAL_OUT)
    n = len(model.centres)
    for k in range(n):
        comp.newparam(f"ball-{k}-present", hal.HAL_BIT, hal.HAL_RW)
        comp[f"ball-{k}-present"] = bool(model.present[k])
    comp.ready()
    out, contacts, last, still_since = False, 0, None, time.monotonic()
    t_ready = still_since
    try:
        while True:
            for k in range(n):
                model.present[k] = bool(comp[f"ball-{k}-present"])
            q = tuple(comp[j] for j in JOINTS)
            now = time.monotonic()
            for a in "xyz":
                comp[f"temp-{a}"] = sensor_c(thermal, a, now - t_ready)
            if q != last:
                last, still_since = q, now
            gap = model.gap_mm(*q)
            plane = model.plane(*q)
            if plane is None:
                comp["plane-k"] = 1e6  # disarm first: never a half-written plane that trips
                for p in PLANE_PINS[:3]:
                    comp[p] = 0.0
            else:
                for p, v in zip(PLANE_PINS, plane, strict=True):
                    comp[p] = v
            hit = gap <= 0.0
            if hit and not out:
                contacts += 1
                comp["contacts"] = contacts
            elif out and not hit:
                model.redraw_touch()  # the probe re-arms: next touch, new noise
            out = hit
            comp["out"] = out
            comp["gap-um"] = gap * 1e3
            comp["crash"] = gap < -CRASH_MM
            if hit or now - still_since > MAX_POLL_S:
                time.sleep(MAX_POLL_S)
            elif gap > BUSY_GAP_MM:
                time.sleep(min(gap / MAX_SPEED_MM_S / 2.0, MAX_POLL_S))
    except KeyboardInterrupt:
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
