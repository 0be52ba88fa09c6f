"""End-to-end start-of-shift runs per transport (the path of tests/test_e2e_transports.py): the
14-pose annex-B plan (280 touches) at time scale 0, wall time from the CNC's request to the
verdict on the CNC side, split into capture / identify+judge+report / write-back, and the
daemon's overhead per touch = (capture wall − simulated machine time × time scale) / touches.

``python -m benchmarks bench_e2e`` (figures printed; nothing asserted). Serial at 921 600 baud
and at 115 200 baud (the program's bytes at the line rate are printed: the pacing floor).
"""

from __future__ import annotations

import asyncio
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PLAN = "thesis_annexB_14poses"
TIME_SCALE = 0.0  # VirtualController default in the rigs: as fast as the control executes


async def one(transport: str, dialect: str, baud: int | None = None,
              floor_s: float = 0.0) -> None:
    from benchmarks.rigs import rig_helpers
    from benchmarks.rigs.e2e_run import run_start_of_shift
    from simulators.controller import VirtualController

    line_rate = rig_helpers.BAUD
    if baud is not None:  # the rig's serial line rate, read when the rig starts
        rig_helpers.BAUD = baud
    try:
        ctrl = VirtualController(rig_helpers.make_truth(), time_scale=TIME_SCALE)
        rig = await rig_helpers.start_rig(transport, ctrl)
    finally:
        rig_helpers.BAUD = line_rate
    try:
        with tempfile.TemporaryDirectory(dir=ROOT) as tmp:  # the project's disk, not tmpfs
            r = await run_start_of_shift(rig, dialect, Path(tmp), PLAN)
    finally:
        await rig.close()
    m, t0, n = r["marks"], r["t0"], r["run"].hits
    if r["state"].value != "IDLE" or "IDENTIFY" not in m:
        print(f"{transport:13s} {dialect}: run ended {r['state']}: {r['reason']}")
        return
    capture = m["IDENTIFY"] - m["STREAM"]
    sim = r["machine_s"] * TIME_SCALE
    label = f"{transport}@{baud}" if baud else transport
    print(f"{label:20s} {dialect:10s} {n} touches: request→verdict on CNC {r['wall_s']:.2f} s "
          f"(trigger→stream {m['STREAM'] - t0:.2f} s, capture {capture:.2f} s, "
          f"identify+judge+report {m['WRITE-BACK'] - m['IDENTIFY']:.2f} s, write-back→CNC "
          f"{t0 + r['wall_s'] - m['WRITE-BACK']:.2f} s); machine time {r['machine_s']:.0f} s "
          f"× {TIME_SCALE:g}; overhead {(capture - sim) / n * 1e3:.1f} ms per touch "
          f"(target ≤ 20 ms)" + (f", {(capture - max(sim, floor_s)) / n * 1e3:.1f} ms beyond "
                                  f"the line rate" if floor_s else ""))


def program_bytes(dialect: str) -> int:
    """Bytes the DNC link sends for the annex-B program (7E1 framing: 10 bits/char)."""
    from contracts.setup_files import load_artefact, load_machine, load_plan
    from drivers.serial.link import frame_program
    from programs.dialects import get_dialect
    from programs.toolpath import build_program

    cfg = ROOT / "config"
    m, mf = load_machine(cfg / "machines/thesis_wcbxfzyt.yaml")
    a = load_artefact(cfg / "artefacts/thesis_4ball.yaml")
    p = load_plan(cfg / f"plans/{PLAN}.yaml")
    text = get_dialect(dialect).render(build_program(m, mf, a, p))
    return len(frame_program(text, "LF", True))


def main() -> None:
    sys.path.insert(0, str(ROOT))  # tests.* rigs
    nbytes = program_bytes("fanuc")
    floor = {baud: nbytes / (baud / 10) for baud in (921_600, 115_200)}
    for baud, f in floor.items():
        print(f"serial pacing floor, fanuc program {nbytes} B at {baud} baud 7E1: {f:.2f} s")
    for transport in ("opcua", "modbus"):
        asyncio.run(one(transport, "fanuc"))
    for transport, baud in (("serial-pty", 921_600), ("serial-socket", 921_600),
                            ("serial-pty", 115_200)):
        asyncio.run(one(transport, "fanuc", baud, floor[baud]))


if __name__ == "__main__":
    main()
