"""systemd's notification protocol (``Type=notify``, ``WatchdogSec=``) with the standard library:
READY=1 once serving, WATCHDOG=1 from the event loop, STOPPING=1 on the way out.

The messages are datagrams to the AF_UNIX socket named by ``$NOTIFY_SOCKET`` (a path, or an
abstract name written with a leading ``@``), as sd_notify(3) specifies. Without systemd (no
``NOTIFY_SOCKET``) every call is a no-op. The watchdog pings come from a task of the daemon's own
event loop: a loop that hangs (a blocking call, a deadlock) stops them, and systemd restarts the
unit after ``WatchdogSec``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import socket
from collections.abc import Mapping

log = logging.getLogger("rumba.sdnotify")


def _address(env: Mapping[str, str]) -> str | None:
    addr = env.get("NOTIFY_SOCKET", "")
    if not addr or not (addr.startswith("/") or addr.startswith("@")):
        return None  # unset, or a vsock address this daemon does not speak
    return "\0" + addr[1:] if addr.startswith("@") else addr


def notify(state: str, env: Mapping[str, str] | None = None) -> bool:
    """Send ``state`` (e.g. ``"READY=1\\nSTATUS=serving"``) to systemd; False when not under
    systemd or the socket is gone (never raises: a lost notification must not stop a run)."""
    addr = _address(os.environ if env is None else env)
    if addr is None:
        return False
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as s:
            s.connect(addr)
            s.sendall(state.encode("utf-8"))
    except OSError as e:
        log.warning("systemd notification %r not sent: %s", state.split("\n")[0], e)
        return False
    return True


def watchdog_interval_s(env: Mapping[str, str] | None = None) -> float | None:
    """Half of ``WATCHDOG_USEC`` (systemd's advice), or None when no watchdog is asked for this
    process (unset, zero, or ``WATCHDOG_PID`` naming another process)."""
    env = os.environ if env is None else env
    pid = env.get("WATCHDOG_PID")
    if pid and pid.strip() != str(os.getpid()):
        return None
    try:
        usec = int(env.get("WATCHDOG_USEC", "0"))
    except ValueError:
        return None
    return usec / 2e6 if usec > 0 else None


async def watchdog(interval_s: float) -> None:
    """Ping the watchdog every ``interval_s`` until cancelled."""
    while True:
        notify("WATCHDOG=1")
        await asyncio.sleep(interval_s)


def start_watchdog() -> asyncio.Task | None:
    """The watchdog task when systemd asked for one (``WatchdogSec=`` in the unit), else None."""
    interval = watchdog_interval_s()
    if interval is None or _address(os.environ) is None:
        return None
    return asyncio.get_running_loop().create_task(watchdog(interval), name="sd-watchdog")


async def stop_watchdog(task: asyncio.Task | None) -> None:
    if task is not None:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
