"""Local LinuxCNC helper: answers the linuxcncrsh command subset drivers/linuxcnc/link.py uses, on
stdin/stdout, through LinuxCNC's own ``linuxcnc`` Python module (daemon on the LinuxCNC PC).

Run by the link with Debian's ``/usr/bin/python3`` — the ``linuxcnc`` module is built for it
only, not for the daemon's venv. One command per line in, one reply line out:
``set estop off|on``, ``set machine on|off``, ``set mode manual|mdi|auto``, ``set home -1``,
``set mdi LINE`` (answers when the block is done, polled every 2 ms: linuxcncrsh and
``command.wait_complete`` both poll in 100 ms steps), ``set abort``, ``get joint_homed``,
``get error`` and ``get operator_display`` (the message channel read into one lossless queue;
each of these takes the oldest message of its kind), and for AUTO runs:

* ``set open PATH`` — ``program_open`` (an absolute path on this PC);
* ``set run`` — ``auto(AUTO_RUN, 0)``; answers once LinuxCNC took it (the command itself stays
  in progress until the program ends, so it is not waited for);
* ``set plan_init`` — ``reset_interpreter()`` (linuxcncrsh's name): unloads the program file.
  LinuxCNC reopens the loaded file after an MDI O-word call (a remap such as ``M429``): once the
  file is deleted that fails ("cannot reopen file … removed or renamed?"), so the link unloads
  it before deleting it. Like M2 it resets the modal state; it also zeroes the volatile numbered
  parameters (#1-#5000);
* ``wait event SECONDS`` — blocks until the oldest message, in channel order, or the end:
  ``EVENT DISPLAY text`` (operator display/text: ``(DEBUG,…)``), ``EVENT ERROR <line> text``
  (``<line>``: ``stat.motion_line`` when it arrived, the program line LinuxCNC stopped at),
  ``EVENT IDLE`` (interpreter idle and every message read), ``EVENT NONE`` (still running).

A killed LinuxCNC leaves its NML shared memory behind and ``stat`` keeps answering the last
state, so every wait also checks that the task process (INI ``[TASK] TASK``) is alive; if it is
gone the helper prints ``LOST …`` and exits. When its stdin closes (the daemon stopped or
dropped the link) while a program it started still runs, it aborts that program, and unloads
the file it opened if LinuxCNC still has it loaded.
"""

from __future__ import annotations

import os
import sys
import time
from collections import deque

TIMEOUT_S = 600.0
POLL_S = 0.002


class Lost(Exception):
    """The LinuxCNC task process is gone (killed or crashed)."""


def _task_pids(ini: str) -> tuple[str, list[int]]:
    """The task process name of the INI ([TASK] TASK, default milltask) and its live PIDs."""
    name, section = "milltask", ""
    try:
        with open(ini, encoding="utf-8", errors="replace") as fh:
            for line in fh:
                s = line.strip()
                if s.startswith("["):
                    section = s
                elif section == "[TASK]" and s.split("=", 1)[0].strip() == "TASK" and "=" in s:
                    name = os.path.basename(s.split("=", 1)[1].split()[0])
    except (OSError, IndexError):
        pass
    pids = []
    for p in os.listdir("/proc"):
        if p.isdigit():
            try:
                with open(f"/proc/{p}/comm") as fh:
                    if fh.read().strip() == name[:15]:
                        pids.append(int(p))
            except OSError:
                continue
    return name, pids


def main() -> int:
    # the script's own folder (the link's modules) comes first in sys.path: drop it, so that
    # nothing there can ever shadow LinuxCNC's `linuxcnc` module
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
    task_name, task_pids = _task_pids(stat.ini_filename)
    if not task_pids:
        print(f"NAK LinuxCNC not running (no {task_name} process)", flush=True)
        return 2
    events: deque[tuple[str, str, int]] = deque()  # (ERROR|DISPLAY, text, motion line)
    error_kinds = {linuxcnc.NML_ERROR, linuxcnc.OPERATOR_ERROR}
    running = [False]  # a program this helper started may still run
    opened = [""]  # the program file this helper opened
    last_alive = [0.0]

    def alive() -> None:
        now = time.monotonic()
        if now - last_alive[0] < 0.05:
            return
        last_alive[0] = now
        if not any(os.path.exists(f"/proc/{p}") for p in task_pids):
            raise Lost(f"LinuxCNC stopped: its task process {task_name} "
                       f"(pid {', '.join(map(str, task_pids))}) is gone")

    def drain() -> None:
        while True:
            m = chan.poll()
            if not m:
                return
            kind, text = m
            stat.poll()
            events.append(("ERROR" if kind in error_kinds else "DISPLAY",
                           " ".join(text.split()), stat.motion_line))

    def take(kind: str) -> str:
        drain()
        for i, ev in enumerate(events):
            if ev[0] == kind:
                del events[i]
                return ev[1]
        return "OK"

    def done(what: str, timeout_s: float = TIMEOUT_S) -> str:
        """Wait for the command's completion, polling every 2 ms (``wait_complete`` sleeps to
        the next 100 ms boundary between checks)."""
        serial = cmd.serial
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            stat.poll()
            if stat.echo_serial_number >= serial and stat.state != linuxcnc.RCS_EXEC:
                return f"SET {what} {'NAK' if stat.state == linuxcnc.RCS_ERROR else 'ACK'}"
            alive()
            time.sleep(POLL_S)
        return f"SET {what} NAK timeout"

    def started() -> str:
        """``auto(AUTO_RUN)`` stays in progress while the program runs: wait until LinuxCNC
        took it and the interpreter left idle (or the command already ended)."""
        serial = cmd.serial
        end = time.monotonic() + 30.0
        while time.monotonic() < end:
            stat.poll()
            if stat.echo_serial_number >= serial:
                if stat.state == linuxcnc.RCS_ERROR:
                    return "SET RUN NAK"
                if stat.interp_state != linuxcnc.INTERP_IDLE or stat.state == linuxcnc.RCS_DONE:
                    running[0] = True
                    return "SET RUN ACK"
            alive()
            time.sleep(POLL_S)
        return "SET RUN NAK timeout"

    def event(timeout_s: float) -> str:
        end = time.monotonic() + timeout_s
        while True:
            drain()
            if events:
                kind, text, line = events.popleft()
                return f"EVENT ERROR {line} {text}" if kind == "ERROR" else f"EVENT DISPLAY {text}"
            stat.poll()
            if stat.interp_state == linuxcnc.INTERP_IDLE:
                drain()  # messages sent just before the end come first
                if not events:
                    running[0] = False
                    return "EVENT IDLE"
                continue
            alive()
            if time.monotonic() > end:
                return "EVENT NONE"
            time.sleep(POLL_S)

    modes = {"manual": linuxcnc.MODE_MANUAL, "mdi": linuxcnc.MODE_MDI, "auto": linuxcnc.MODE_AUTO}
    print("HELLO ACK rumba-local 1.1", flush=True)
    try:
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
                elif key == "set open":
                    path = raw.strip()[len("set open"):].strip()
                    if not os.path.isabs(path) or not os.path.isfile(path):
                        raise ValueError(f"no program file {path}")
                    cmd.program_open(path)
                    out = done("OPEN")
                    opened[0] = path
                elif key == "set run":
                    cmd.auto(linuxcnc.AUTO_RUN, 0)
                    out = started()
                elif key == "set plan_init":
                    cmd.reset_interpreter()
                    out = done("PLAN_INIT")
                elif key == "set abort":
                    cmd.abort()
                    out = done("ABORT")
                    running[0] = False
                elif key == "wait event":
                    out = event(min(float(words[2]), 60.0))
                elif key == "get joint_homed":
                    stat.poll()
                    out = "JOINT_HOMED " + " ".join("YES" if h else "NO"
                                                    for h in stat.homed[:stat.joints])
                elif key == "get error":
                    out = "ERROR " + take("ERROR")
                elif key == "get operator_display":
                    out = "OPERATOR_DISPLAY " + take("DISPLAY")
                else:
                    out = f"{' '.join(words[:2]).upper()} NAK"
            except (linuxcnc.error, KeyError, IndexError, ValueError) as e:
                out = f"{' '.join(words[:2]).upper()} NAK {e}"
            print(out.replace("\n", " "), flush=True)
    except Lost as e:
        print(f"LOST {e}", flush=True)
        return 3
    try:
        stat.poll()
        if running[0] and stat.interp_state != linuxcnc.INTERP_IDLE:
            cmd.abort()  # the daemon let go while our program runs: never leave it unattended
            done("ABORT", 2.0)
            stat.poll()
        if opened[0] and stat.file == opened[0]:
            cmd.reset_interpreter()
            done("PLAN_INIT", 2.0)
    except (Lost, linuxcnc.error):
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
