"""End-to-end check of the LinuxCNC peer (stdlib only; any python3).

    python3 tests/peers/linuxcnc/rsh_smoke.py [--kins xyzbc|xyzac]

Starts LinuxCNC headless with start_linuxcnc.sh and the trivial probe component, then over
linuxcncrsh on 127.0.0.1: hello, enable, estop off, machine on, home all, an MDI move in
identity kinematics, M428 (TCP kinematics) with joint positions checked against the trtfuncs
inverse formulas, G38.2 against the probe (results #5061-#5070 through (LOG,…) and (DEBUG,…)),
a G38.2 miss, and shutdown. Also runs `rs274 -g` on a G38.2 file. Prints one line per step
with its duration and exits non-zero on the first failure.
"""

import argparse
import math
import os
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
# sample-config values, set by its [HAL]HALCMD lines (start_linuxcnc.sh keeps them)
OFFSETS = {"xyzbc": {"x": -20.0, "y": 0.0, "z": -15.0}, "xyzac": {"x": 0.0, "y": 20.0, "z": 10.0}}


def inverse(kins, x, y, z, r, c, dt=0.0):
    """World (tool tip in table coordinates) -> joint XYZ, trtfuncs.c with rot-points 0."""
    o = OFFSETS[kins]
    rr, cr = math.radians(r), math.radians(c)
    cs, sn, cc, sc = math.cos(rr), math.sin(rr), math.cos(cr), math.sin(cr)
    if kins == "xyzbc":
        dx, dz = o["x"], o["z"] + dt
        return (
            cc * cs * x - sc * cs * y + sn * z - cs * dx - sn * dz + dx,
            sc * x + cc * y,
            -cc * sn * x + sc * sn * y + cs * z + sn * dx - cs * dz + dz,
        )
    dy, dz = o["y"], o["z"] + dt
    return (
        cc * x - sc * y,
        sc * cs * x + cc * cs * y - sn * z - cs * dy + sn * dz + dy,
        sc * sn * x + cc * sn * y + cs * z - sn * dy - cs * dz + dz,
    )


class Rsh:
    """Line-oriented linuxcncrsh client: replies end in \\r\\n (get) or \\n\\r (set ACKs)."""

    def __init__(self, port):
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=60)
        self.buf = b""

    def line(self):
        while True:
            m = re.search(rb"[^\r\n]+[\r\n]", self.buf)  # first complete non-empty line
            if m:
                self.buf = self.buf[m.end() :]
                return m.group()[:-1].decode()
            data = self.sock.recv(4096)
            if not data:
                raise ConnectionError("linuxcncrsh closed the connection")
            self.buf += data

    def send(self, cmd):
        self.sock.sendall(cmd.encode() + b"\r\n")

    def ask(self, cmd):
        self.send(cmd)
        return self.line()

    def drain_errors(self):
        errs = []
        for _ in range(20):
            e = self.ask("get error")
            if e.strip() == "ERROR OK":
                return errs
            errs.append(e)
        return errs


def step(name, t0, detail=""):
    print(f"ok   {name:<34} {time.monotonic() - t0:6.2f}s  {detail}", flush=True)


def fail(msg):
    print(f"FAIL {msg}", flush=True)
    sys.exit(1)


def wait_until(pred, timeout, what):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return
        time.sleep(0.1)
    fail(f"timeout waiting for {what}")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--kins", choices=("xyzbc", "xyzac"), default="xyzbc")
    args = ap.parse_args()
    rot = "B" if args.kins == "xyzbc" else "A"
    tmp = Path(tempfile.mkdtemp(prefix="rumba-lcnc-smoke."))
    env = dict(os.environ, HOME=str(tmp))
    lcnc_dir = None
    try:
        # rs274 standalone interpreter
        t0 = time.monotonic()
        (tmp / "p.ngc").write_text("G21 G90\nG0 X0 Y0 Z10\nG38.2 Z-5 F100\nM2\n")
        subprocess.run(
            ["rs274", "-g", str(tmp / "p.ngc"), str(tmp / "out.txt")],
            env=env,
            stdin=subprocess.DEVNULL,
            capture_output=True,
            check=True,
        )
        canon = (tmp / "out.txt").read_text()
        if "STRAIGHT_PROBE(0.0000, 0.0000, -5.0000" not in canon:
            fail("rs274: no STRAIGHT_PROBE\n" + canon)
        step("rs274 -g prints STRAIGHT_PROBE", t0)

        t0 = time.monotonic()
        out = subprocess.run(
            [
                "bash",
                str(HERE / "start_linuxcnc.sh"),
                "--kins",
                args.kins,
                "--probe-comp",
                str(HERE / "probe_comp.py"),
                "--halcmd",
                "net probe-z joint.2.pos-fb => rumba-probe.z",
            ],
            capture_output=True,
            text=True,
            check=False,
        )
        if out.returncode:
            fail("start_linuxcnc.sh\n" + out.stderr)
        info = dict(ln.split("=", 1) for ln in out.stdout.split())
        lcnc_dir, port, pid = info["LCNC_DIR"], int(info["LCNC_PORT"]), int(info["LCNC_PID"])
        step("start (linuxcncrsh listening)", t0, f"port {port} pid {pid}")

        t0 = time.monotonic()
        r = Rsh(port)
        if not r.ask("hello EMC rumba 1.0").startswith("HELLO ACK"):
            fail("hello")
        r.send("set echo off")  # itself echoed (or not, if sent early): sync on "get echo"
        r.send("get echo")
        while r.line() != "ECHO OFF":
            pass
        for cmd in (
            "set verbose on",
            "set enable EMCTOO",
            "set estop off",
            "set machine on",
            "set set_wait done",
            "set mode manual",
            "set home -1",
        ):
            rep = r.ask(cmd)
            if not rep.endswith("ACK"):
                fail(f"{cmd}: {rep}")
        wait_until(lambda: r.ask("get joint_homed").split()[1:6] == ["YES"] * 5, 20, "homing")
        step("hello/enable/estop off/on/home", t0, r.ask("get machine"))

        def mdi(block):
            # with set_wait done the reply comes when the block has finished; NAK if rejected
            # up front (limits, "Start point too close to probe point"); a failure during the
            # move (probe miss, probe trip during G0) still answers ACK: read "get error".
            if r.ask("set mode mdi") != "SET MODE ACK":
                fail("mode mdi")
            rep = r.ask(f"set mdi {block}")
            if rep != "SET MDI ACK":
                fail(f"mdi {block}: {rep} {r.drain_errors()}")

        def joints():
            return [float(v) for v in r.ask("get joint_pos").split()[1:6]]

        t0 = time.monotonic()
        r.drain_errors()
        mdi(f"G0 X10 Y5 Z-1 {rot}5 C30")
        pos, jp = r.ask("get abs_act_pos"), joints()
        errs = r.drain_errors()
        if jp != [10.0, 5.0, -1.0, 5.0, 30.0] or errs:
            fail(f"identity move: {pos} {jp} {errs}")
        step("MDI move, identity kins", t0, f"{pos} / joints {jp}")

        t0 = time.monotonic()
        mdi("M428")
        worst = 0.0
        for pose in [(10, 5, 20, 20, 30), (0, 0, 30, -35, 100), (-7, 12, 25, 10, -45)]:
            want = inverse(args.kins, *pose)
            mdi("G0 X{} Y{} Z{} {}{} C{}".format(*pose[:3], rot, *pose[3:]))
            got = joints()
            if errs := r.drain_errors():
                fail(f"M428 pose {pose}: {errs}")
            worst = max(worst, *(abs(g - w) for g, w in zip(got[:3], want, strict=True)))
        if worst > 2e-6:
            fail(f"joint positions differ from the trtfuncs formulas by {worst}")
        step(f"M428 {args.kins} kins vs formulas", t0, f"max |joint - formula| = {worst:.1e} mm")

        t0 = time.monotonic()
        mdi("M429")
        mdi(f"G0 X0 Y0 Z0 {rot}0 C0")
        log = Path(lcnc_dir) / "nc_files" / "probe.log"
        prog = Path(lcnc_dir) / "nc_files" / "probe.ngc"
        prog.write_text(
            "G21 G90\nG0 X0 Y0 Z0\nG38.2 Z-10 F100\n"
            f"(LOGOPEN,{log})\n"
            "(LOG,#5061 #5062 #5063 #5064 #5065 #5066 #5067 #5068 #5069 #5070)\n(LOGCLOSE)\n"
            "(DEBUG,probe z=#5063 ok=#5070)\nG0 Z0\nM2\n"
        )
        for cmd in ("set mode auto", f"set open {prog}", "set run"):
            if not r.ask(cmd).endswith("ACK"):
                fail(cmd)
        time.sleep(0.3)
        wait_until(lambda: r.ask("get program_status") == "PROGRAM_STATUS IDLE", 30, "program")
        vals = [float(v) for v in log.read_text().split()]
        if errs := r.drain_errors():
            fail(f"probe program: {errs}")
        if vals[9] != 1.0 or not -2.01 < vals[2] <= -2.0:
            fail(f"probe result {vals}")
        step(
            "G38.2 latches via HAL probe",
            t0,
            f"#5063={vals[2]:.6f} #5070={vals[9]:.0f}; {r.ask('get operator_display')}",
        )

        t0 = time.monotonic()
        r.ask("set mode manual")
        mdi("G38.2 Z-1 F200")
        errs = r.drain_errors()
        if not any("without making contact" in e for e in errs):
            fail(f"G38.2 miss: {errs}")
        step("G38.2 miss reported by get error", t0, errs[-1])

        t0 = time.monotonic()
        r.send("shutdown")
        wait_until(lambda: not Path(f"/proc/{pid}").exists(), 20, "linuxcnc exit")
        step("shutdown", t0)
    finally:
        if lcnc_dir:
            subprocess.run(
                ["bash", str(HERE / "start_linuxcnc.sh"), "--stop", lcnc_dir], check=False
            )
        shutil.rmtree(tmp, ignore_errors=True)
    print("1 passed, 0 failed")


if __name__ == "__main__":
    main()
