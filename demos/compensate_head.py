"""Compensation demo on a swivel head: LinuxCNC 2.9 headless with rumba's kins module
``xyzbc_head_kins`` (config/linuxcnc/xyzbc_head_kins.comp, built with halcompile), the HAL
probe carrying injected head and table link errors — verification run, ``rumba compensate
--confirm`` (the module's pins set live with halcmd, the HAL file patched), second verification
run against the compensated controller, the compensable links before and after.

``python -m demos.compensate_head [--plan F] [--out DIR]`` (needs `bash .ci/install-peers.sh
linuxcnc`, root to install the module). Exit 0 only when every compensable link of the first run
is within its expanded uncertainty of zero after (k·u_c, k the 99.73 % Student t, as
demos.compensate) and the link-caused distortion RMS fell by at least 90 %.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import yaml

from demos import linuxcnc
from demos.compensate import DEMO_GUARDS, judge, verification
from demos.linuxcnc import CONFIG, run_demo

MACHINE_NAME = "lcnc-head"
MACHINE = "machines/linuxcnc_swivelhead.yaml"
ARTEFACT = "artefacts/vertical_4ball.yaml"
ERRORS = "errors/linuxcnc_swivelhead.yaml"
INI = "rumba_swivelhead.ini"
PLAN = CONFIG / "plans/linuxcnc_swivelhead_9poses.yaml"
PINS = ["xyzbc-head-kins.c-x", "xyzbc-head-kins.ea0c-deg", "xyzbc-head-kins.eb0c-deg",
        "xyzbc-head-kins.ea0b-deg", "xyzbc-head-kins.ec0b-deg"]


def daemon_yaml(work: Path, port: int, plan: Path, machine_file: Path) -> str:
    """The demo's daemon.yaml (demos.linuxcnc.daemon_yaml): the swivel head, ``machine_file``
    with DEMO_GUARDS."""
    return linuxcnc.daemon_yaml(work, port, plan, writer="demos/compensate_head.py",
                                name=MACHINE_NAME, machine_file=machine_file,
                                artefact=CONFIG / ARTEFACT)


def demo_machine_file(work: Path, unattended: bool = False) -> Path:
    """The head machine file with the demo's guards (demos.compensate.DEMO_GUARDS)."""
    data = yaml.safe_load((CONFIG / MACHINE).read_text(encoding="utf-8"))
    data["controller_kinematics"]["guards"] = dict(DEMO_GUARDS, unattended=unattended)
    path = work / "linuxcnc_swivelhead.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path


def start_peer(work: Path):  # type: ignore[no-untyped-def]
    """LinuxCNC (rumba_swivelhead.ini) in ``work/linuxcnc``, the HAL probe carrying ``ERRORS``:
    (the TruthModel, the running peer)."""
    from simulators import linuxcnc_peer
    from simulators.hal_probe import write_spec
    from simulators.truth import TruthModel

    truth = TruthModel.from_files(CONFIG / MACHINE, CONFIG / ARTEFACT, CONFIG / ERRORS)
    spec = work / "probe_spec.json"
    write_spec(truth, spec)
    return truth, linuxcnc_peer.up(spec, workdir=work / "linuxcnc", ini_name=INI)


async def demo(plan: Path, work: Path) -> int:
    from daemon.cli.main import main as rumba
    from drivers.linuxcnc import halkins
    from simulators import linuxcnc_peer

    t0 = time.monotonic()
    truth, peer = start_peer(work)
    fifo = (peer.dir / "fifo.path").read_text().strip()
    os.environ["RTAPI_FIFO_PATH"] = f"{fifo}/rtapi_fifo"  # halcmd of this process → this HAL
    print(f"LinuxCNC up (xyzbc_head_kins, linuxcncrsh 127.0.0.1:{peer.port}); HAL probe truth "
          f"{ERRORS}: " + ", ".join(f"{k} {v:+g}" for k, v in truth.errors.links.items()))
    try:
        cfg = work / "daemon.yaml"
        cfg.write_text(daemon_yaml(work, peer.port, plan, demo_machine_file(work)))
        run1 = await verification(cfg, "verification before", MACHINE_NAME)
        live0 = halkins.read_pins(PINS)
        t1 = time.monotonic()
        code = rumba(["compensate", "--config", str(cfg), "--confirm", run1, "--by", "demo"])
        print(f"rumba compensate --confirm: exit {code} ({time.monotonic() - t1:.2f} s)")
        if code != 0:
            return 1
        live1 = halkins.read_pins(PINS)
        print("kins pins: " + ", ".join(f"{p} {live0[p]:g} -> {live1[p]:g}" for p in PINS))
        run2 = await verification(cfg, "verification after", MACHINE_NAME)
        out = judge(cfg, run1, run2, MACHINE_NAME)
        print("\ncompensable links before / after compensation:")
        for line in out.lines:
            print("  " + line)
        print(f"\n{'PASS' if out.ok else 'FAIL'}: demo wall time {time.monotonic() - t0:.1f} s; "
              f"journal, reports and config in {work}")
        return 0 if out.ok else 1
    finally:
        linuxcnc_peer.down(peer.dir)


def main(argv: list[str] | None = None) -> int:
    from simulators.linuxcnc_headkins import HeadKinsError
    from simulators.linuxcnc_peer import PeerError

    return run_demo("demos.compensate_head", "rumba-demo-head-", demo,
                    (PeerError, HeadKinsError, RuntimeError), argv, description=__doc__,
                    raw_description=True, default_plan=PLAN)


if __name__ == "__main__":
    sys.exit(main())
