"""``rumba fleet --store postgresql://… --token-file F``: serve the read-only fleet page over
the PostgreSQL fleet store (loopback by default; TLS like the HMI's)."""

from __future__ import annotations

import argparse
import asyncio
import signal
from pathlib import Path
from typing import Any

from aiohttp import web

from daemon.cli.main import UserError
from daemon.config import read_token_file
from daemon.hosts import is_loopback
from daemon.store.url import parse_store_url


def _listen(value: str) -> tuple[str, int]:
    host, sep, port = value.rpartition(":")
    if not sep or not host or not port.isdigit() or int(port) > 65535:
        raise UserError(f"--listen: expected HOST:PORT, got {value!r}")
    return host.strip("[]"), int(port)


def cmd_fleet(args: argparse.Namespace) -> int:
    import logging

    from daemon.fleet.app import create_fleet_app
    from daemon.hmi.auth import SECRET_FILE, SecretError, load_or_create_secret
    from daemon.hmi.tls import server_context
    from daemon.service.logs import setup_terminal_logging

    setup_terminal_logging(logging.INFO)  # the store's outages and returns, one line each
    url = parse_store_url(args.store, "--store")
    if url.kind != "postgresql":
        raise UserError("--store: the fleet page reads the PostgreSQL fleet store "
                        "(postgresql://…), not a single machine's sqlite journal")
    host, port = _listen(args.listen)
    if args.stale_after_h <= 0:
        raise UserError("--stale-after-h: expected a positive number of hours")
    token = read_token_file(args.token_file, "--token-file")
    for d in args.reports_dir:
        if not d.is_dir():
            raise UserError(f"--reports-dir: {d} is not a directory")
    if (args.tls_cert is None) != (args.tls_key is None):
        raise UserError("--tls-cert and --tls-key go together")
    ctx = server_context(args.tls_cert, args.tls_key, "--tls") if args.tls_cert else None
    if ctx is None and not is_loopback(host):
        print(f"warning: serving on {host} without TLS: the token and session cookies cross "
              "the network in clear text (--tls-cert/--tls-key)", flush=True)
    try:
        secret = (load_or_create_secret(args.state_dir / SECRET_FILE)
                  if args.state_dir else None)
    except SecretError as e:
        raise UserError(str(e)) from None
    app = create_fleet_app(url.dsn or "", token, stale_after_h=args.stale_after_h,
                           reports_dirs=args.reports_dir, secure_cookie=ctx is not None,
                           secret=secret, bind_host=host, public_origins=args.public_origin)
    opcua = _opcua_config(args.opcua) if args.opcua is not None else None
    if args.opcua_poll_s <= 0:
        raise UserError("--opcua-poll-s: expected a positive number of seconds")
    asyncio.run(_serve(app, host, port, ctx, opcua, url.dsn or "", args.opcua_poll_s))
    return 0


def _opcua_config(path: Path) -> Any:
    """The OPC UA results server's settings: daemon.yaml's opcua_server keys, in a file of
    their own (relative paths from its folder); any machine name may carry identification."""
    from contracts.yaml_files import ConfigError, read_yaml, validate_file
    from daemon.opcua.config import OpcUaServerFile, load_opcua_server

    p = path
    try:
        f = validate_file(OpcUaServerFile, p, read_yaml(p))
        return load_opcua_server(f, p.parent, str(p), list(f.machines), read_token_file)
    except ConfigError as e:
        raise UserError(str(e)) from None


async def _start_opcua(cfg: Any, dsn: str, poll_s: float) -> tuple[Any, Any]:
    """The fleet store's machines over OPC UA: one endpoint for the shop."""
    from contracts.yaml_files import ConfigError
    from daemon.opcua.server import OpcUaServerError, ResultServer
    from daemon.opcua.source import FleetSource
    from daemon.service.heap import freeze_startup_heap
    from daemon.store.journal import StoreError
    from daemon.store.pg import PgStore

    try:
        pg = await PgStore.connect(dsn, app="rumba-fleet-opcua", migrate=False)
    except StoreError as e:
        raise UserError(str(e)) from None
    source = FleetSource(pg)
    server = ResultServer(cfg, source, await source.machines())
    try:
        url = await server.start()
    except (OpcUaServerError, ConfigError) as e:
        await server.stop()
        await pg.close()
        raise UserError(f"--opcua: {e}") from None
    server.follow(poll_s)
    freeze_startup_heap()
    print(f"rumba fleet: OPC UA results {url}", flush=True)
    return server, pg


async def _store_reachable(dsn: str) -> None:
    """The fleet store answers before the page is served: a page that could only answer 503
    is not started (while it serves, an outage is said on the terminal and the page answers
    503 until the store is back)."""
    from daemon.store.journal import StoreError
    from daemon.store.pg import PgStore

    try:
        store = await PgStore.connect(dsn, app="rumba-fleet", migrate=False)
    except StoreError as e:
        raise UserError(f"--store: {e} (is PostgreSQL running and reachable?)") from None
    await store.close()


async def _serve(app: web.Application, host: str, port: int, ctx: object,
                 opcua: Any = None, dsn: str = "", poll_s: float = 5.0) -> None:
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    await _store_reachable(dsn)
    runner = web.AppRunner(app, access_log=None, handle_signals=False)
    await runner.setup()
    site = web.TCPSite(runner, host, port, ssl_context=ctx)  # type: ignore[arg-type]
    try:
        await site.start()
    except OSError as e:
        await runner.cleanup()
        raise UserError(f"--listen: cannot listen on {host}:{port}: {e.strerror}") from None
    bound = runner.addresses[0][1] if runner.addresses else port
    scheme = "https" if ctx else "http"
    print(f"rumba fleet: {scheme}://{host}:{bound}/", flush=True)
    server = pg = None
    try:
        if opcua is not None:
            server, pg = await _start_opcua(opcua, dsn, poll_s)
        await stop.wait()
    finally:
        if server is not None:
            await server.stop()
        if pg is not None:
            await pg.close()
        await runner.cleanup()
