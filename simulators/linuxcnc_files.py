"""The files a headless LinuxCNC instance of simulators/linuxcnc_peer.py runs on: the HAL probe's
net file (the trip evaluated in the servo thread) and the machine's INI patched for linuxcncrsh
on a port, the instance's program folder and that HAL file."""

from __future__ import annotations

import json
import re
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent

# The trip decided in the servo thread (simulators/hal_probe.py): u = U·q (mult2, sum2), for each
# ball K d_K = |u − m_K| (sum2, hypot) against the contact radius r_K and r_K − 0.1 mm (comp).
# The userspace component publishes U, m_K, r_K once per indexation behind a window on B and C
# (wcomp): a stale or half-written set is never used. A touch reaches motion.probe-input only
# while LinuxCNC runs a probing move (motion.motion-type 5), so nothing becomes an edge during
# the retract ("Probe tripped during non-probe move"); a collision (crash, in the servo thread
# or the component's consistent snapshot) trips in any move. Signal rumba-probe-hold: a probing
# move without its indexation's set (never netted to motion.feed-inhibit: netted, LinuxCNC's
# AUTO race came 5 runs in 6 under load, config/linuxcnc/README.md).
_U = {"x": ["u00"], "y": ["u01", "u11"], "z": ["u02", "u12", "u22"]}


def _or_chain(name: str, inputs: list[str], load: dict[str, list[str]],
              lines: list[str]) -> str:
    """OR ``inputs`` (signal names) with or2 ``name-K``; returns the signal of the result."""
    acc = inputs[0]
    for k, sig in enumerate(inputs[1:], 1):
        load["or2"].append(f"{name}-{k}")
        lines += [f"net {acc} => {name}-{k}.in0", f"net {sig} => {name}-{k}.in1",
                  f"net {name}-any{k} {name}-{k}.out"]
        acc = f"{name}-any{k}"
    return acc


def probe_net(n_balls: int) -> str:
    """The servo-thread half of the HAL probe for ``n_balls`` balls (HAL lines)."""
    if n_balls < 1:
        raise ValueError("the HAL probe needs at least one ball")
    load: dict[str, list[str]] = {k: [] for k in ("mult2", "sum2", "hypot", "comp", "or2",
                                                   "and2", "not", "wcomp", "conv_s32_float")}
    lines: list[str] = []
    for i, names in enumerate(_U.values()):
        for u in names:
            load["mult2"].append(f"rumba-{u}")
            lines += [f"net rumba-j{i} => rumba-{u}.in0",
                      f"net rumba-{u}-k rumba-probe.{u} => rumba-{u}.in1",
                      f"net rumba-{u}-q rumba-{u}.out"]
    load["sum2"] += ["rumba-ux01", "rumba-ux", "rumba-uy"]
    lines += ["net rumba-u00-q => rumba-ux01.in0", "net rumba-u01-q => rumba-ux01.in1",
              "net rumba-ux01-q rumba-ux01.out => rumba-ux.in0",
              "net rumba-u02-q => rumba-ux.in1", "net rumba-ux rumba-ux.out",
              "net rumba-u11-q => rumba-uy.in0", "net rumba-u12-q => rumba-uy.in1",
              "net rumba-uy rumba-uy.out"]
    u_sig = {"x": "rumba-ux", "y": "rumba-uy", "z": "rumba-u22-q"}
    touch, crash = [], []
    for k in range(n_balls):
        b = f"rumba-b{k}"
        for i, a in enumerate("xyz"):
            load["sum2"].append(f"{b}-d{a}")
            lines += [f"net {u_sig[a]} => {b}-d{a}.in0",
                      f"net {b}-m{a} rumba-probe.ball-{k}-{a} => {b}-d{a}.in1",
                      f"setp {b}-d{a}.gain1 -1", f"net {b}-d{a} {b}-d{a}.out => {b}-d.in{i}"]
        load["hypot"].append(f"{b}-d")
        load["comp"] += [f"{b}-touch", f"{b}-crash"]
        lines += [f"net {b}-dist {b}-d.out => {b}-touch.in0 {b}-crash.in0",
                  f"net {b}-r rumba-probe.ball-{k}-r => {b}-touch.in1",
                  f"net {b}-crash-r rumba-probe.ball-{k}-crash-r => {b}-crash.in1",
                  f"net {b}-touching {b}-touch.out", f"net {b}-crashing {b}-crash.out"]
        touch.append(f"{b}-touching")
        crash.append(f"{b}-crashing")
    touch_any = _or_chain("rumba-touch", touch, load, lines)
    crash_any = _or_chain("rumba-crash", crash, load, lines)
    load["wcomp"] += ["rumba-valid-b", "rumba-valid-c", "rumba-probing"]
    load["conv_s32_float"].append("rumba-mtype")
    load["and2"] += ["rumba-valid", "rumba-touch-valid", "rumba-probe-gate", "rumba-crash-valid",
                     "rumba-hold"]
    load["not"].append("rumba-invalid")
    load["or2"] += ["rumba-crash-either", "rumba-probe-any"]
    lines += [
        "net rumba-j3 => rumba-valid-b.in", "net rumba-j4 => rumba-valid-c.in",
        *(f"net rumba-{a}-{e} rumba-probe.{a}-{e} => rumba-valid-{a}.{e}"
          for a in "bc" for e in ("min", "max")),
        "net rumba-valid-b rumba-valid-b.out => rumba-valid.in0",
        "net rumba-valid-c rumba-valid-c.out => rumba-valid.in1",
        "net rumba-valid rumba-valid.out => rumba-touch-valid.in1 rumba-crash-valid.in1 "
        "rumba-invalid.in",
        f"net {touch_any} => rumba-touch-valid.in0", f"net {crash_any} => rumba-crash-valid.in0",
        "net rumba-motion-type motion.motion-type => rumba-mtype.in",
        "net rumba-motion-type-f rumba-mtype.out => rumba-probing.in",
        "setp rumba-probing.min 4.5", "setp rumba-probing.max 5.5",
        "net rumba-is-probing rumba-probing.out => rumba-probe-gate.in1 rumba-hold.in1",
        "net rumba-touch-valid rumba-touch-valid.out => rumba-probe-gate.in0",
        "net rumba-invalid rumba-invalid.out => rumba-hold.in0",
        "net rumba-probe-hold rumba-hold.out",  # not netted to motion.feed-inhibit: README
        "net rumba-crash-valid rumba-crash-valid.out => rumba-crash-either.in0",
        "net rumba-probe-crash rumba-probe.crash => rumba-crash-either.in1",
        "net rumba-crash-either rumba-crash-either.out => rumba-probe-any.in1",
        "net rumba-probe-gated rumba-probe-gate.out => rumba-probe-any.in0",
        "net rumba-probe-trip rumba-probe-any.out => motion.probe-input"]
    head = [f"loadrt {kind} names={','.join(names)}" for kind, names in load.items() if names]
    # functions in data order: each servo period computes the trip from that period's joints
    last = ["rumba-valid", "rumba-invalid", "rumba-touch-valid", "rumba-probe-gate",
            "rumba-crash-valid", "rumba-hold", "rumba-crash-either", "rumba-probe-any"]
    funcs = [n for kind in ("mult2", "sum2", "hypot", "comp", "or2", "conv_s32_float", "wcomp")
             for n in load[kind] if n not in last] + last
    return "\n".join(head + [f"addf {n} servo-thread" for n in funcs] + lines) + "\n"


def write_probe_hal(path: Path, spec: Path) -> None:
    """The HAL file that loads simulators/hal_probe.py on ``spec`` (userspace), feeds it the
    five joint positions and decides the trip in the servo thread (probe_net, one chain per
    ball of the spec)."""
    n = len(json.loads(spec.read_text(encoding="utf-8"))["ball_ids"])
    lines = [f"loadusr -Wn rumba-probe /usr/bin/python3 {REPO}/simulators/hal_probe.py "
             f"{spec.resolve()}"]
    lines += [f"net rumba-j{i} joint.{i}.pos-fb => rumba-probe.{j}"
              for i, j in enumerate("xyzbc")]
    lines += probe_net(n).splitlines()
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
