"""Local LinuxCNC helper: answers the linuxcncrsh command subset drivers/linuxcnc.py uses, on
stdin/stdout, through LinuxCNC's own ``linuxcnc`` Python module (daemon on the LinuxCNC PC).

Run by the link with Debian's ``/usr/bin/python3`` — the ``linuxcnc`` module is built for it
only, not for the daemon's venv. One command per line in, one reply line out:
``set estop off|on``, ``set machine on|off``, ``set mode manual|mdi|auto``, ``set home -1``,
``set mdi LINE`` (answers when the block is done, polled every 2 ms: linuxcncrsh and
``command.wait_complete`` both poll in 100 ms steps), ``set abort``, ``get joint_homed``,
``get error`` and ``get operator_display`` (the message channel sorted into two lossless queues).
"""

from __future__ import annotations

import os
import sys
import time
from collections import deque

TIMEOUT_S = 600.0
POLL_S = 0.002


def main() -> int:
    # this file sits next to drivers/linuxcnc.py, which would shadow the `linuxcnc` module
    here = os.path.dirname(os.path.abspath(__file__))
    sys.path[:] = [p for p in sys.path if os.path.abspath(p or ".") != here]
    try:
        import linuxcnc
    except ImportError as e:
        print(f"NAK no linuxcnc module in {sys.executable}: {e}", flush=True)
        return 2
    try:
        stat, cmd, chan = linuxcnc.stat(), linuxcnc.command(), linuxcnc.error_channel()
        stat.poll()
    except linuxcnc.error as e:
        print(f"NAK LinuxCNC not running: {e}", flush=True)
        return 2
    errors: deque[str] = deque()
    displays: deque[str] = deque()
    error_kinds = {linuxcnc.NML_ERROR, linuxcnc.OPERATOR_ERROR}

    def drain() -> None:
        while True:
            m = chan.poll()
            if not m:
                return
            kind, text = m
            (errors if kind in error_kinds else displays).append(" ".join(text.split()))

    def done(what: str) -> str:
        """Wait for the command's completion, polling every 2 ms (``wait_complete`` sleeps to
        the next 100 ms boundary between checks)."""
        serial = getattr(cmd, "serial", None)
        if serial is None:
            r = cmd.wait_complete(TIMEOUT_S)
            return f"SET {what} {'NAK' if r == linuxcnc.RCS_ERROR or r == -1 else 'ACK'}"
        end = time.monotonic() + TIMEOUT_S
        while time.monotonic() < end:
            stat.poll()
            if stat.echo_serial_number >= serial and stat.state != linuxcnc.RCS_EXEC:
                return f"SET {what} {'NAK' if stat.state == linuxcnc.RCS_ERROR else 'ACK'}"
            time.sleep(POLL_S)
        return f"SET {what} NAK timeout"

    modes = {"manual": linuxcnc.MODE_MANUAL, "mdi": linuxcnc.MODE_MDI, "auto": linuxcnc.MODE_AUTO}
    print("HELLO ACK rumba-local 1.0", flush=True)
    for raw in sys.stdin:
        words = raw.split()
        if not words:
            continue
        key = " ".join(words[:2]).lower()
        try:
            if key == "set estop":
                cmd.state(linuxcnc.STATE_ESTOP_RESET if words[2] == "off"
                          else linuxcnc.STATE_ESTOP)
                out = done("ESTOP")
            elif key == "set machine":
                cmd.state(linuxcnc.STATE_ON if words[2] == "on" else linuxcnc.STATE_OFF)
                out = done("MACHINE")
            elif key == "set mode":
                cmd.mode(modes[words[2]])
                out = done("MODE")
            elif key == "set home":
                cmd.home(int(words[2]))
                out = done("HOME")
            elif key == "set mdi":
                cmd.mdi(raw.strip()[len("set mdi"):].strip())
                out = done("MDI")
            elif key == "set abort":
                cmd.abort()
                out = done("ABORT")
            elif key == "get joint_homed":
                stat.poll()
                out = "JOINT_HOMED " + " ".join("YES" if h else "NO"
                                                for h in stat.homed[:stat.joints])
            elif key == "get error":
                drain()
                out = "ERROR " + (errors.popleft() if errors else "OK")
            elif key == "get operator_display":
                drain()
                out = "OPERATOR_DISPLAY " + (displays.popleft() if displays else "OK")
            else:
                out = f"{' '.join(words[:2]).upper()} NAK"
        except (linuxcnc.error, KeyError, IndexError, ValueError) as e:
            out = f"{' '.join(words[:2]).upper()} NAK {e}"
        print(out.replace("\n", " "), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
