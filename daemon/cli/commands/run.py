"""``rumba run --config daemon.yaml``: start the verification service (sessions, triggers, HMI)."""

from __future__ import annotations

import argparse
import asyncio
import logging
import signal

from daemon.cli.main import UserError
from daemon.config import load_daemon_config
from daemon.service import sdnotify
from daemon.service.heap import freeze_startup_heap
from daemon.service.logs import setup_logging
from daemon.service.service import Service, ServiceError
from daemon.store.journal import StoreError


async def serve(service: Service) -> None:
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    sdnotify.notify("STATUS=connecting to the controllers")
    try:
        await service.start()
    except (ServiceError, StoreError) as e:
        raise UserError(str(e)) from None
    freeze_startup_heap()
    names = ", ".join(f"{n} ({s.setup.link.transport}, {s.setup.dialect})"
                      for n, s in service.sessions.items())
    print(f"rumba: serving {names}", flush=True)
    if service.interrupted:
        print(f"rumba: marked interrupted: {', '.join(service.interrupted)}", flush=True)
    if service.hmi_url:
        print(f"rumba: HMI at {service.hmi_url}", flush=True)
    # systemd (Type=notify): ready once every link is up and the HMI listens; the watchdog
    # pings come from this event loop, so a hung loop gets the unit restarted.
    sdnotify.notify(f"READY=1\nSTATUS=serving {names}")
    watchdog = sdnotify.start_watchdog()
    try:
        await stop.wait()
    finally:
        sdnotify.notify("STOPPING=1\nSTATUS=stopping: aborting runs, closing links")
        await sdnotify.stop_watchdog(watchdog)
        await service.stop()
        print("rumba: stopped", flush=True)


def cmd_run(args: argparse.Namespace) -> int:
    max_mb = getattr(args, "log_max_mb", 10)
    if not 1 <= max_mb <= 10_000:
        raise UserError(f"--log-max-mb {max_mb}: expected 1 to 10000 (MiB per log file)")
    repeats = setup_logging(logging.DEBUG if args.verbose else logging.INFO,
                            getattr(args, "log_file", None), max_bytes=max_mb * 1024 * 1024)
    cfg = load_daemon_config(args.config)
    if args.check:
        print(f"{args.config}: OK ({len(cfg.machines)} machines: {', '.join(cfg.machines)})")
        return 0
    try:
        asyncio.run(serve(Service(cfg)))
    finally:
        repeats.flush()
    return 0
