"""``rumba sim --serve serial|opcua|modbus|can|sinumerik|lsv2|haas``: one VirtualController
behind one protocol front-end, listening on loopback until interrupted; prints where it listens
(one ``listening:`` line per endpoint, flushed, so a script can read it). Typing ``request`` on
stdin raises the start-of-shift request as the CNC's PLC would; ``run FILE`` loads a program and
cycle-starts it as the operator at the control does (a confirmed compensation program);
``abort`` resets the control; ``quit`` stops (``start`` / ``abort``: the CAN panel's buttons, or
a SINUMERIK's NC start and RESET).
"""

from __future__ import annotations

import argparse
import asyncio
import glob
import os
import secrets
import signal
import stat
import sys
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any


class ServeError(Exception):
    """The front-end could not start (port in use, device missing): one line for the CLI."""


def add_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("serve (controller-side protocol front-ends)")
    g.add_argument("--serve", choices=["serial", "opcua", "modbus", "can", "sinumerik", "lsv2",
                                       "haas"],
                   help="serve the simulated controller over this transport")
    g.add_argument("--host", default="127.0.0.1", help="bind address (default 127.0.0.1)")
    g.add_argument("--port", type=int, help="TCP port (default: a free one; serial: a pty "
                   "unless a port is given, 0 for any free one)")
    g.add_argument("--raise-request", type=float, metavar="S",
                   help="raise the start-of-shift request S seconds after start")
    g.add_argument("--baud", type=int, default=115200, help="serial: baud rate (pacing)")
    g.add_argument("--framing", choices=["7E1", "8N1", "7E2", "8N2"], default="7E1",
                   help="serial: character framing (default 7E1)")
    g.add_argument("--rx-buffer", type=int, default=256, help="serial: receive buffer bytes")
    g.add_argument("--security", default="Basic256Sha256_SignAndEncrypt",
                   choices=["Basic256Sha256_SignAndEncrypt", "Basic256Sha256_Sign", "none"],
                   help="opcua: security policy (none only for tests)")
    g.add_argument("--cert-dir", type=Path, default=Path("sim-pki"),
                   help="opcua: folder for the server certificate (made on first start)")
    g.add_argument("--trust", type=Path, metavar="DIR",
                   help="opcua: accept only client certificates found in DIR")
    g.add_argument("--share", type=Path,
                   help="haas: the folder the machine reads O09100.nc from (its network share)")
    g.add_argument("--no-plc-start", action="store_true",
                   help="sinumerik, lsv2, haas: nothing starts rumba's program by itself "
                        "(type 'start' for the operator's NC start)")
    g.add_argument("--user", default="rumba", help="opcua: user name (password from "
                   "$RUMBA_SIM_PASSWORD, else generated and printed)")
    g.add_argument("--device-id", type=int, default=1, help="modbus: unit id")
    g.add_argument("--can-interface", default="virtual", help="can: python-can interface")
    g.add_argument("--can-channel", default="rumba", help="can: channel")
    g.add_argument("--can-base-id", type=lambda s: int(s, 0), default=0x640,
                   help="can: base identifier of the panel frames")


def serve(args: argparse.Namespace) -> int:
    """Entry point used by daemon/cli/commands/sim.py (synchronous: runs its own event loop)."""
    return asyncio.run(serve_async(args))


def _say(text: str) -> None:
    print(text, flush=True)


async def serve_async(args: argparse.Namespace) -> int:
    from simulators.controller import VirtualController

    truth = args.truth
    seed = args.seed if args.seed is not None else getattr(truth, "seed", 0)
    # the control's own dialect: what a drip-fed tape and a program run at the console are in
    ctrl = VirtualController(truth, time_scale=args.time_scale, rng_seed=seed or 0,
                             faults=getattr(args, "fault_plan", None),
                             dialect=getattr(args, "dialect", None) or "fanuc")
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    try:
        closer, panel = await _start(args, ctrl)
    except (OSError, ValueError) as e:
        raise ServeError(f"--serve {args.serve}: {e}") from None
    tasks = [asyncio.create_task(_stdin(ctrl, stop, panel, getattr(args, "dialect", None)))]
    if args.raise_request is not None:
        async def later() -> None:
            await asyncio.sleep(args.raise_request)
            ctrl.raise_start_request()
            _say("start-of-shift request raised")
        tasks.append(asyncio.create_task(later()))
    try:
        await stop.wait()
    finally:
        for t in tasks:
            t.cancel()
        await closer()
    return 0


async def _start(args: argparse.Namespace, ctrl: Any) -> tuple[Any, Any]:
    kind = args.serve
    if kind == "serial":
        from simulators.frontends.serial import SerialFrontend, SerialSettings

        fe = SerialFrontend(ctrl, SerialSettings(baudrate=args.baud, framing=args.framing,
                                                 rx_buffer_bytes=args.rx_buffer))
        # One port, one sender: a pty (the default), or raw TCP with --port (a serial-to-
        # Ethernet converter's socket://). Both at once cannot work: the pty's session holds
        # the port for good, so a TCP sender would be turned away at once.
        try:
            if args.port is None:
                _say(f"listening: {await fe.open_pty()}")
            else:
                _say(f"listening: socket://{args.host}:{await fe.open_tcp(args.host, args.port)}")
        except OSError:
            await fe.close()
            raise
        _say(f"serial: {args.baud} baud {args.framing}, XON/XOFF, receive buffer "
             f"{args.rx_buffer} bytes")
        return fe.close, None
    if kind in ("opcua", "sinumerik"):
        from simulators.frontends.opcua import OpcUaFrontend
        from simulators.frontends.sinumerik import SinumerikFrontend

        users = None
        if args.security != "none":
            password = os.environ.get("RUMBA_SIM_PASSWORD") or secrets.token_urlsafe(12)
            users = {args.user: password}
            if "RUMBA_SIM_PASSWORD" not in os.environ:
                _say(f"opcua user: {args.user} password: {password}")
        trusted = [args.trust] if args.trust else None
        panel = None
        if kind == "sinumerik":
            ctrl.dialect = "siemens"
            fe = SinumerikFrontend(ctrl, security=args.security, cert_dir=args.cert_dir,
                                   users=users, trusted_client_certs=trusted,
                                   plc_starts=not args.no_plc_start)
            panel = _MachinePanel(fe)
        else:
            fe = OpcUaFrontend(ctrl, security=args.security, cert_dir=args.cert_dir,
                               users=users, trusted_client_certs=trusted)
        url = await fe.start(args.host, args.port or 0)
        _say(f"listening: {url}")
        if panel is not None:
            _say("sinumerik: type 'start' for NC start, 'abort' for RESET at the machine")
        if fe.server_certificate is not None:
            _say(f"server certificate: {fe.server_certificate}")
        if args.security != "none" and trusted is None:
            _say("note: any valid client certificate is accepted (give --trust DIR to pin)")
        return fe.stop, panel
    if kind == "lsv2":
        from simulators.frontends.lsv2 import Lsv2Frontend

        ctrl.dialect = "heidenhain"
        fe = Lsv2Frontend(ctrl, auto_start=None if args.no_plc_start else "TNC:\\RUMBA\\RUMBA.H")
        port = await fe.start(args.host, args.port or 0)
        _say(f"listening: lsv2://{args.host}:{port} (TNC640; type 'start' for NC start of "
             "TNC:\\RUMBA\\RUMBA.H, 'abort' for internal stop)")
        return fe.stop, _MachinePanel(fe, lambda: fe.nc_start("TNC:\\RUMBA\\RUMBA.H"))
    if kind == "haas":
        from simulators.frontends.haas import HaasFrontend

        if args.share is None or not args.share.is_dir():
            raise ValueError("--share DIR (an existing folder: the machine's network share)")
        ctrl.dialect = "haas"
        fe = HaasFrontend(ctrl, args.share, auto_start=not args.no_plc_start)
        port = await fe.start(args.host, args.port or 0)
        _say(f"listening: haas-mdc://{args.host}:{port} share {args.share} (type 'start' "
             "for cycle start of O09100, 'abort' for RESET)")
        return fe.stop, _MachinePanel(fe, fe.cycle_start)
    if kind == "modbus":
        from simulators.frontends.modbus import ModbusFrontend

        fe = ModbusFrontend(ctrl, device_id=args.device_id)
        port = await fe.start(args.host, args.port or 0)
        _say(f"listening: modbus-tcp://{args.host}:{port} unit {args.device_id}")
        return fe.stop, None
    import can

    from simulators.frontends.can import SimulatedPanel

    try:
        bus = can.Bus(interface=args.can_interface, channel=args.can_channel)
    except (can.CanError, ImportError) as e:
        raise OSError(f"cannot open {args.can_interface} bus {args.can_channel!r}: {e}") from None
    panel = SimulatedPanel(bus, base_id=args.can_base_id)
    _say(f"listening: can {args.can_interface}:{args.can_channel} base id "
         f"{args.can_base_id:#05x} (type 'start' or 'abort' to press a button)")
    return panel.close, panel


class _MachinePanel:
    """The machine's NC start and RESET keys, for a control that offers no remote start."""

    def __init__(self, frontend: Any, start: Callable[[], Awaitable[None]] | None = None
                 ) -> None:
        self.fe = frontend
        self.start = start or frontend.nc_start
        self._tasks: set[asyncio.Task] = set()

    def press(self, button: str) -> None:
        coro = self.start() if button == "start" else self.fe.ctrl.abort()
        task = asyncio.get_running_loop().create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)


async def _line_reader(f: Any) -> Callable[[], Awaitable[bytes]] | None:
    """Lines of ``f`` without blocking the loop: a pipe, socket or terminal through the loop; a
    regular file or ``/dev/null`` (``< /dev/null``, a service manager), which epoll cannot
    watch, in a thread; None when there is nothing to read."""
    try:
        fd = f.fileno()
        mode = os.fstat(fd).st_mode
    except (OSError, ValueError):
        return None  # closed
    if not (stat.S_ISFIFO(mode) or stat.S_ISSOCK(mode) or os.isatty(fd)):
        return lambda: asyncio.to_thread(f.buffer.readline)
    reader = asyncio.StreamReader()
    try:
        await asyncio.get_running_loop().connect_read_pipe(
            lambda: asyncio.StreamReaderProtocol(reader), f)
    except (ValueError, OSError):
        return None
    return reader.readline


async def _stdin(ctrl: Any, stop: asyncio.Event, panel: Any = None,
                 dialect: str | None = None) -> None:
    """Operator commands from stdin until it ends; the simulator keeps serving after that."""
    if sys.stdin is None or sys.stdin.closed:
        return
    readline = await _line_reader(sys.stdin)
    if readline is None:
        return
    while line := await readline():
        cmd = line.decode(errors="replace").strip().lower()
        if cmd == "request":
            ctrl.raise_start_request()
            _say("start-of-shift request raised")
        elif cmd in ("start", "abort") and panel is not None:
            panel.press(cmd)
        elif cmd == "abort":
            await ctrl.abort()
        elif cmd == "quit":
            stop.set()
            return
        elif cmd.startswith("run ") or cmd == "run":
            _say(await _run_at_console(ctrl, line.decode(errors="replace").strip()[3:].strip(),
                                       dialect))
        elif cmd:
            _say(f"unknown command {cmd!r} (request, run FILE, abort, quit)")


async def _run_at_console(ctrl: Any, name: str, dialect: str | None) -> str:
    """``run FILE``: what the operator does with a program at the control — load it, cycle
    start, wait for its end; one line saying how it ended. A pattern (``*.mpf``) runs the
    newest file it matches, as an operator picks the latest program in the list."""
    if not name:
        return "run: name the program file, e.g. run ~/reports/compensation_*.mpf"
    if dialect is None:
        return "run: the control's dialect is not known: start rumba sim with --dialect"
    path = Path(os.path.expanduser(name))
    if glob.has_magic(name):
        found = [Path(f) for f in glob.glob(str(path)) if os.path.isfile(f)]
        if not found:
            return f"run: no file matches {path}"
        path = max(found, key=lambda f: f.stat().st_mtime_ns)
    try:
        if not path.is_file():
            return f"run: {path}: not a file"
        text = path.read_text(encoding="utf-8")
        await ctrl.load_program(text, dialect)
        await ctrl.start()
        state = await ctrl.wait_done(120)
    except (OSError, UnicodeDecodeError, RuntimeError, ValueError, TimeoutError) as e:
        return f"run: {path}: {e}"
    alarm = f": {ctrl.alarm}" if state == "alarm" and ctrl.alarm else ""
    return f"ran {path.name}: {state}{alarm}"
