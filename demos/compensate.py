"""Compensation demo: LinuxCNC 2.9 headless (xyzbc-trt-kins, HAL probe carrying the demo link
errors) — verification run, ``rumba compensate --confirm`` (kins pins set live with halcmd, the
HAL file patched), second verification run identified against the compensated controller, and
the pivot errors before and after.

``python -m demos.compensate [--plan F] [--out DIR]`` (needs `bash .ci/install-peers.sh
linuxcnc`; ~5 min with the default 7-pose plan, 3 min with linuxcnc_4poses). Exit 0 only
when every compensable link of the first run is within its expanded uncertainty of zero after
(k·u_c, both runs' u combined, k the 99.73 % Student t) and the link-caused distortion RMS
(daemon/analysis/figures.py) fell by at least 90 %.
"""

from __future__ import annotations

import math
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import yaml

from daemon.analysis import figures
from demos import linuxcnc
from demos.linuxcnc import CONFIG, ERRORS, MACHINE, run_demo, start_peer

MACHINE_NAME = "lcnc-trt"
# The demo's EX0C (−106 µm) is over KinematicsOpt's 50 µm per value: the demo's copy of the
# machine file pins its own guards (150 µm per value, 200 µm in total), whatever the shipped
# file says.
DEMO_GUARDS = {"max_change_um": 150, "max_change_urad": 100, "max_total_um": 200,
               "unattended": False}
COVERAGE = 0.9973  # the pass test's coverage (as tests/test_linuxcnc_e2e.py: Student t)


def daemon_yaml(work: Path, port: int, plan: Path, machine_file: Path) -> str:
    """The demo's daemon.yaml (demos.linuxcnc.daemon_yaml): ``machine_file`` with DEMO_GUARDS."""
    return linuxcnc.daemon_yaml(work, port, plan, writer="demos/compensate.py",
                                name=MACHINE_NAME, machine_file=machine_file)


def demo_machine_file(work: Path) -> Path:
    """The LinuxCNC machine file with the demo's guards (DEMO_GUARDS)."""
    data = yaml.safe_load((CONFIG / MACHINE).read_text(encoding="utf-8"))
    data["controller_kinematics"]["guards"] = dict(DEMO_GUARDS)
    path = work / "linuxcnc_xyzbc.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path


@dataclass
class Outcome:
    ok: bool
    lines: list[str]
    before: dict[str, tuple[float, float]]  # compensable link → (value, std), µm / µrad
    after: dict[str, tuple[float, float]]
    distortion_before_um: float  # link-caused distortion RMS (daemon/analysis/figures.py)
    distortion_after_um: float


async def verification(cfg: Path, label: str, machine: str = MACHINE_NAME) -> str:
    """One verification run (``rumba verify``), identified against the controller model of
    the journal; its run id."""
    from daemon.cli.commands.verify import verify
    from daemon.compensation.propose import journal_analyse
    from daemon.config import load_daemon_config
    from daemon.store.journal import Store

    t0 = time.monotonic()
    store_path = load_daemon_config(cfg).store_path
    code = await verify(str(cfg), machine, quiet=True,
                        analyse=journal_analyse(store_path))
    store = Store(store_path)
    try:
        run_id = store.runs(machine, 1)[0].id
    finally:
        store.close()
    print(f"{label}: run {run_id} exit {code} ({time.monotonic() - t0:.1f} s)")
    if code == 2:
        raise RuntimeError(f"{label}: verification run {run_id} ended in ERROR")
    return run_id


def judge(cfg: Path, run1: str, run2: str, machine: str = MACHINE_NAME) -> Outcome:
    """Before/after from both runs re-identified against the controller model of their time."""
    from daemon.compensation.propose import propose
    from daemon.config import load_daemon_config
    from daemon.store.journal import Store
    from identification.estimate import coverage_factor

    conf = load_daemon_config(cfg)
    setup = conf.machines[machine]
    store = Store(conf.store_path)
    try:
        p1, p2 = propose(setup, store, run1), propose(setup, store, run2)
        dof = min(store.analysis(r).estimation.sigma_dof or math.inf  # type: ignore[union-attr]
                  for r in (run1, run2))
    finally:
        store.close()
    k = coverage_factor(dof, COVERAGE)
    comp = [n for n, v in p1.plan.links_compensable.items()
            if abs(v) > 1e-3 * max(abs(p1.plan.links_identified[n]), 1e-9)]
    lines, ok = [], True
    before = {n: p1.links[n][:2] for n in comp}
    after = {n: p2.links[n][:2] for n in comp}
    for n in comp:
        (v1, u1), (v2, u2) = before[n], after[n]
        unit = p1.links[n][2].replace("urad", "µrad").replace("um", "µm")
        uc = math.hypot(u1, u2)  # the zero it is tested against carries run 1's uncertainty
        inside = abs(v2) <= k * uc
        ok &= inside
        lines.append(f"{n}: before {v1:+.2f} ± {2 * u1:.2f} {unit}, after {v2:+.2f} ± "
                     f"{2 * u2:.2f} {unit} (U, k=2); |after| {'<=' if inside else '>'} "
                     f"{k:.2f}·u_c = {k * uc:.2f} {unit}")
    # the figures of daemon/analysis/figures.py, by their names and definitions:
    # run 1's link-caused distortion and its predicted after compensation, against the
    # link-caused distortion the verification run measures
    f1, f2 = p1.figures(), p2.figures()
    by1 = {f.key: f for f in f1}
    by2 = {f.key: f for f in f2}
    d1 = p1.plan.distortion_before_um[0]
    d2 = p2.plan.distortion_before_um[0]
    fall = 1.0 - d2 / d1 if d1 > 0 else 0.0
    ok &= bool(comp) and fall >= 0.9
    for key in (figures.LINK_CAUSED_RMS, figures.LINK_CAUSED_MAX):
        lines.append(f"{by1[key].text(1)} before; verification run: {by2[key].value:.1f} "
                     f"{by2[key].unit}")
    for key in (figures.PREDICTED_RMS, figures.PREDICTED_MAX):
        lines.append(f"{by1[key].text(1)} (run 1's plan)")
    lines.append(f"link-caused distortion RMS {100 * fall:.1f} % less (≥ 90 % required)")
    for key in (figures.LINK_CAUSED_MAX, figures.PREDICTED_MAX):
        lines.append(f"  {by1[key].label}: {by1[key].definition}")
    return Outcome(ok, lines, before, after, d1, d2)


async def demo(plan: Path, work: Path) -> int:
    from daemon.cli.main import main as rumba
    from drivers.linuxcnc import halkins
    from simulators import linuxcnc_peer

    t0 = time.monotonic()
    truth, peer = start_peer(work)
    fifo = (peer.dir / "fifo.path").read_text().strip()
    os.environ["RTAPI_FIFO_PATH"] = f"{fifo}/rtapi_fifo"  # halcmd of this process → this HAL
    print(f"LinuxCNC up (linuxcncrsh 127.0.0.1:{peer.port}); HAL probe truth {ERRORS}: "
          + ", ".join(f"{k} {v:+g}" for k, v in truth.errors.links.items()))
    try:
        cfg = work / "daemon.yaml"
        cfg.write_text(daemon_yaml(work, peer.port, plan, demo_machine_file(work)))
        run1 = await verification(cfg, "verification before")
        pins = ["xyzbc-trt-kins.x-offset", "xyzbc-trt-kins.z-offset"]
        live0 = halkins.read_pins(pins)
        t1 = time.monotonic()
        code = rumba(["compensate", "--config", str(cfg), "--confirm", run1, "--by", "demo"])
        print(f"rumba compensate --confirm: exit {code} ({time.monotonic() - t1:.2f} s)")
        if code != 0:
            return 1
        live1 = halkins.read_pins(pins)
        print("kins pins: " + ", ".join(f"{p} {live0[p]:g} -> {live1[p]:g}" for p in pins))
        run2 = await verification(cfg, "verification after")
        rumba(["compensate", "--config", str(cfg), run2])  # what is left (proposal only)
        out = judge(cfg, run1, run2)
        print("\npivot errors before / after compensation:")
        for line in out.lines:
            print("  " + line)
        print(f"\n{'PASS' if out.ok else 'FAIL'}: demo wall time {time.monotonic() - t0:.1f} s; "
              f"journal, reports and config in {work}")
        return 0 if out.ok else 1
    finally:
        linuxcnc_peer.down(peer.dir)


def main(argv: list[str] | None = None) -> int:
    from simulators.linuxcnc_peer import PeerError

    return run_demo("demos.compensate", "rumba-demo-comp-", demo, (PeerError, RuntimeError),
                    argv, description=__doc__, raw_description=True)


if __name__ == "__main__":
    sys.exit(main())
