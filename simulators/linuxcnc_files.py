"""The files a headless LinuxCNC instance of simulators/linuxcnc_peer.py runs on: the HAL probe's
net file (the trip evaluated in the servo thread) and the machine's INI patched for linuxcncrsh
on a port, the instance's program folder and that HAL file."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent

# The trip evaluated in the servo thread (simulators/hal_probe.py "Latency"): plane distance
# g = wx·X + wy·Y + wz·Z + k (mult2 + sum2: pins, not params), comp.out = (0 > g), OR the
# component's own test — both only while LinuxCNC runs a probing move (motion.motion-type 5):
# the userspace half lags under load, and a plane or contact it publishes late must not reach
# LinuxCNC as a new edge during the retract ("Probe tripped during non-probe move"). A real
# collision (the stylus deep inside a ball, ``rumba-probe.crash``) trips in any move.
PLANE_HAL = """\
loadrt mult2 names=rumba-plane-mx,rumba-plane-my,rumba-plane-mz
loadrt sum2 names=rumba-plane-sxy,rumba-plane-sxyz,rumba-plane-g
loadrt comp names=rumba-plane-cmp
loadrt or2 names=rumba-probe-or,rumba-probe-any
loadrt conv_s32_float names=rumba-mtype
loadrt wcomp names=rumba-probing
loadrt and2 names=rumba-probe-gate
addf rumba-plane-mx servo-thread
addf rumba-plane-my servo-thread
addf rumba-plane-mz servo-thread
addf rumba-plane-sxy servo-thread
addf rumba-plane-sxyz servo-thread
addf rumba-plane-g servo-thread
addf rumba-plane-cmp servo-thread
addf rumba-probe-or servo-thread
addf rumba-mtype servo-thread
addf rumba-probing servo-thread
addf rumba-probe-gate servo-thread
addf rumba-probe-any servo-thread
net rumba-j0 => rumba-plane-mx.in0
net rumba-j1 => rumba-plane-my.in0
net rumba-j2 => rumba-plane-mz.in0
net rumba-plane-wx rumba-probe.plane-wx => rumba-plane-mx.in1
net rumba-plane-wy rumba-probe.plane-wy => rumba-plane-my.in1
net rumba-plane-wz rumba-probe.plane-wz => rumba-plane-mz.in1
net rumba-plane-px rumba-plane-mx.out => rumba-plane-sxy.in0
net rumba-plane-py rumba-plane-my.out => rumba-plane-sxy.in1
net rumba-plane-pxy rumba-plane-sxy.out => rumba-plane-sxyz.in0
net rumba-plane-pz rumba-plane-mz.out => rumba-plane-sxyz.in1
net rumba-plane-pxyz rumba-plane-sxyz.out => rumba-plane-g.in0
net rumba-plane-k rumba-probe.plane-k => rumba-plane-g.in1
net rumba-plane-dist rumba-plane-g.out => rumba-plane-cmp.in0
setp rumba-plane-cmp.in1 0
setp rumba-plane-cmp.hyst 0
net rumba-plane-trip rumba-plane-cmp.out => rumba-probe-or.in0
net rumba-probe-late rumba-probe.out => rumba-probe-or.in1
net rumba-probe-contact rumba-probe-or.out => rumba-probe-gate.in0
net rumba-motion-type motion.motion-type => rumba-mtype.in
net rumba-motion-type-f rumba-mtype.out => rumba-probing.in
setp rumba-probing.min 4.5
setp rumba-probing.max 5.5
net rumba-is-probing rumba-probing.out => rumba-probe-gate.in1
net rumba-probe-gated rumba-probe-gate.out => rumba-probe-any.in0
net rumba-probe-crash rumba-probe.crash => rumba-probe-any.in1
net rumba-probe-trip rumba-probe-any.out => motion.probe-input
"""


def write_probe_hal(path: Path, spec: Path) -> None:
    """The HAL file that loads simulators/hal_probe.py on ``spec`` (userspace), feeds it the
    five joint positions and wires its trip to motion.probe-input through PLANE_HAL."""
    lines = [f"loadusr -Wn rumba-probe /usr/bin/python3 {REPO}/simulators/hal_probe.py "
             f"{spec.resolve()}"]
    lines += [f"net rumba-j{i} joint.{i}.pos-fb => rumba-probe.{j}"
              for i, j in enumerate("xyzbc")]
    lines += PLANE_HAL.splitlines()
    path.write_text("\n".join(lines) + "\n")


def write_ini(src: Path, dst: Path, port: int, nc_dir: Path, probe_hal: Path | None) -> None:
    """``src`` to ``dst`` with [DISPLAY] linuxcncrsh on ``port`` and PROGRAM_PREFIX ``nc_dir``,
    and ``probe_hal`` (when given) loaded right after the machine's own HAL file."""
    out, section = [], ""
    for line in src.read_text().splitlines(keepends=True):
        s = line.strip()
        m = re.match(r"\[(\w+)\]", s)
        if m:
            section = m.group(1)
        key = s.split("=", 1)[0].strip() if "=" in s and not s.startswith("#") else ""
        if section == "DISPLAY" and key == "DISPLAY":
            line = f"DISPLAY = linuxcncrsh --port {port}\n"
        elif section == "DISPLAY" and key == "PROGRAM_PREFIX":
            line = f"PROGRAM_PREFIX = {nc_dir}\n"
        out.append(line)
        if section == "HAL" and key == "HALFILE" and f"{src.stem}.hal" in s and probe_hal:
            out.append(f"HALFILE = {probe_hal}\n")
    dst.write_text("".join(out))
