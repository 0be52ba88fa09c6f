"""Serial DNC streaming throughput against the baud-rate limit (target ≥ 90 %), and XON/XOFF
behaviour with a 256-byte control buffer, over a real pty to the simulator's serial front-end."""

from __future__ import annotations

import asyncio
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


async def _stream(baud: int, time_scale: float, n_poses: int) -> str:
    from benchmarks.rigs.transport_sim import real_setup
    from drivers.serial.link import SerialDncLink
    from drivers.serial.schema import SerialLinkConfig
    from simulators.frontends.serial import SerialFrontend, SerialSettings

    vc, job = real_setup("fanuc", poses=((0.0, 0.0),) * n_poses, time_scale=time_scale)
    fe = SerialFrontend(vc, SerialSettings(baudrate=baud, framing="7E1", rx_buffer_bytes=256))
    link = SerialDncLink(SerialLinkConfig(transport="serial", url=await fe.open_pty(),
                                          baudrate=baud, framing="7E1"))
    await link.connect()
    t = time.perf_counter()
    try:
        hits = [h async for h in link.run(job)]
    finally:
        await link.close()
        await fe.close()
    wall = time.perf_counter() - t
    rate = link.bytes_sent / link.stream_s
    return (f"{baud:>6} baud 7E1, time scale {time_scale:g}: {link.bytes_sent} bytes in "
            f"{link.stream_s:.2f} s = {rate:.0f} char/s = {100 * rate / link.chars_per_s:.1f} % "
            f"of the line ({link.chars_per_s:.0f} char/s); {len(hits)} touches, "
            f"{fe.xoff_sent} XOFF, peak buffer {fe.max_fill}/256, alarms {fe.alarms or 'none'}; "
            f"wall {wall:.2f} s")


def main() -> None:
    sys.path.insert(0, str(ROOT))
    # Time scale 0: the control is never the bottleneck, the line is (throughput).
    for baud in (9600, 38400, 115200):
        print(asyncio.run(_stream(baud, 0.0, 2 if baud < 38400 else 6)))
    # A control slower than the line: XON/XOFF must hold the buffer below 256 bytes.
    print(asyncio.run(_stream(115200, 0.1, 2)))


if __name__ == "__main__":
    main()
