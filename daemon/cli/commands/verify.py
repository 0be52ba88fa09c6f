"""``rumba verify --config daemon.yaml --machine NAME``: one verification run in this process
(CI or by hand), terminal progress; exit code 0 pass (and warn unless --strict), 1 fail, 2 error
(run aborted or failed, or a measurement not trusted); stopped by a signal: 130 (Ctrl-C, SIGINT)
or 143 (SIGTERM), after the run is aborted and journaled and the controller reset.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import os
import signal
from collections.abc import Callable
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn

from daemon.cli.commands.verify_daemon import abort_on_daemon, bar_fields, follow_run
from daemon.cli.commands.verify_map import Prompts, map_exit
from daemon.cli.main import UserError
from daemon.compensation.propose import journal_analyse
from daemon.config import load_daemon_config
from daemon.run.session import Refused, Session
from daemon.service.logs import setup_terminal_logging
from daemon.service.service import LinkFactory, ServiceError, make_link
from daemon.store.journal import Store, StoreError
from drivers.base import LinkError

COLOURS = {"PASS": "bold green", "WARN": "bold yellow", "FAIL": "bold red",
           "ERROR": "bold magenta"}


async def verify(cfg_path: str, machine: str, *, strict: bool = False, quiet: bool = False,
                 link_factory: LinkFactory = make_link, console: Console | None = None,
                 operator: str = "", job: str = "check", **session_kw: Any) -> int:
    cfg = load_daemon_config(cfg_path)
    setup = cfg.machines.get(machine)
    if setup is None:
        raise UserError(f"{cfg_path}: no machine {machine!r} (configured: "
                        f"{', '.join(cfg.machines)})")
    console = console or Console(stderr=True)
    try:
        store = Store(cfg.store_path, cfg.synchronous,  # type: ignore[arg-type]
                      source=f"{cfg.path}: store.path")
    except StoreError as e:
        raise UserError(str(e)) from None
    link = link_factory(setup)
    try:
        try:
            await link.connect()
        except (LinkError, OSError) as e:
            raise UserError(f"machine {machine}: controller unreachable: {e}") from None
        kw = {"analyse": journal_analyse(cfg.store_path), **session_kw}
        session = Session(setup, link, store, cfg.reports_dir, **kw)
        queue = session.subscribe()
        try:
            run_id = session.start("cli", started_by=operator, job=job)
        except Refused as e:
            raise UserError(str(e)) from None

        async def go_on() -> None:
            with contextlib.suppress(Refused):  # the run ended meanwhile
                session.continue_map(operator or "rumba verify")

        prompts = Prompts(console, go_on)
        stopped_by = _stop_on_signals(session, console)
        with Progress(TextColumn("[bold]{task.fields[state]:<10}"), BarColumn(),
                      MofNCompleteColumn(), TextColumn("touches  {task.fields[eta]}"),
                      console=console, disable=quiet, transient=False) as bar:
            task = bar.add_task(run_id, total=None, state="PREPARE", eta="")
            waiter = asyncio.create_task(session.wait())
            while not waiter.done():
                getter = asyncio.create_task(queue.get())
                done, _ = await asyncio.wait({getter, waiter},
                                             return_when=asyncio.FIRST_COMPLETED)
                if getter in done:
                    st = getter.result()
                    prompts.see(st)
                    bar.update(task, total=st["total"] or None, completed=st["done"],
                               **bar_fields(st))
                else:
                    getter.cancel()
            st = session.status()
            bar.update(task, completed=st["done"], **bar_fields(st))
    except ServiceError as e:
        raise UserError(str(e)) from None
    finally:
        # The run has ended (its abort, journal row and controller reset included) before the
        # store and link close: closing them under a live run was the Ctrl-C tracebacks.
        _restore_signals()
        if "prompts" in locals():
            prompts.close()
        with contextlib.suppress(Exception):
            await link.close()
        store.close()
    code = map_exit(run_id, st, console) if job == "map" else \
        _verdict_exit(run_id, st, strict, console)
    return 128 + int(stopped_by[0]) if stopped_by else code


STOP_SIGNALS = {signal.SIGINT: "Ctrl-C (SIGINT)", signal.SIGTERM: "SIGTERM"}


def _stop_on_signals(session: Session, console: Console) -> list[signal.Signals]:
    """SIGINT / SIGTERM abort the run as any other trigger does (controller reset, journal row
    ABORTED naming the signal and the phase); ``verify`` then waits for that end and exits
    128 + the signal number. Returns the list the first signal is recorded in."""
    aborts: list[asyncio.Task] = []
    loop = asyncio.get_running_loop()
    return _catch_signals(console, lambda sig: aborts.append(  # kept: not GC'd
        loop.create_task(session.abort(STOP_SIGNALS[sig]))))


def _catch_signals(console: Console, first: Callable[[signal.Signals], None]
                   ) -> list[signal.Signals]:
    """SIGINT / SIGTERM call ``first`` once (the stop is bounded: a second signal only says
    so); returns the list the first signal is recorded in."""
    loop = asyncio.get_running_loop()
    got: list[signal.Signals] = []

    def on_signal(sig: signal.Signals) -> None:
        if got:
            console.print("[bold]stopping: the run is being aborted and the controller reset, "
                          "please wait[/]")
            return
        got.append(sig)
        first(sig)

    for sig in STOP_SIGNALS:
        loop.add_signal_handler(sig, on_signal, sig)
    return got


def _restore_signals() -> None:
    with contextlib.suppress(Exception):
        loop = asyncio.get_running_loop()
        for sig in STOP_SIGNALS:
            loop.remove_signal_handler(sig)


def _verdict_exit(run_id: str, st: dict[str, Any], strict: bool, console: Console) -> int:
    if st["state"] not in ("IDLE",) or not st.get("verdict"):
        console.print(f"[bold magenta]ERROR[/] run {run_id} {st['state']}: {st['reason']}")
        return 2
    v = st["verdict"]
    console.print(f"[{COLOURS.get(v['status'], 'bold')}]{v['status']}[/] run {run_id}: "
                  f"{v['summary']}")
    for r in v["reasons"]:
        console.print(f"  - {r}")
    if v.get("report_state") == "failed":  # the verdict stands, the report not
        console.print(f"[bold magenta]report not written[/]: {v.get('report_error', '')}")
    if v.get("pdf"):
        print(f"for filing (PDF, A4): {v['pdf']}")
    if v.get("report"):  # the report's JSON is written beside its HTML (report.write_report)
        print(f"numbers (JSON): {Path(v['report']).with_suffix('.json')}")
    print(f"report: {v.get('report')}")  # the last line: scripts read the path from it
    if v["status"] == "ERROR":
        return 2
    return 1 if v["status"] == "FAIL" or (strict and v["status"] == "WARN") else 0


async def verify_via_daemon(cfg_path: str, machine: str, *, strict: bool = False,
                            quiet: bool = False, console: Console | None = None,
                            operator: str = "", job: str = "check") -> int:
    """Trigger the running daemon through its HMI API (bearer token) and follow its events;
    ``operator``: the person journaled as starting the run.
    SIGINT / SIGTERM abort that run on the daemon (HMI abort, same token, naming the signal)
    and return 128 + the signal number once the daemon reports the run ended."""
    import ssl

    import aiohttp

    cfg = load_daemon_config(cfg_path)
    if machine not in cfg.machines:
        raise UserError(f"{cfg_path}: no machine {machine!r} (configured: "
                        f"{', '.join(cfg.machines)})")
    if not cfg.hmi.enabled or cfg.hmi.port == 0:
        raise UserError(f"{cfg_path}: hmi: --daemon needs the HMI enabled on a fixed port")
    console = console or Console(stderr=True)
    scheme = "https" if cfg.hmi_tls else "http"
    base = f"{scheme}://{cfg.hmi.host}:{cfg.hmi.port}/"
    ctx = ssl.create_default_context(cafile=str(cfg.hmi_tls[0])) if cfg.hmi_tls else None
    headers = {"Authorization": f"Bearer {cfg.hmi_token}"}
    stop = asyncio.Event()
    stopped_by = _catch_signals(console, lambda _sig: stop.set())
    try:
        async with aiohttp.ClientSession(headers=headers) as http:
            events = await http.get(base + "api/events", ssl=ctx)
            if stopped_by:  # stopped before anything was started on the daemon
                return 128 + int(stopped_by[0])
            who = {"operator": operator} if operator else {}
            params = {"trigger": "cli", "job": job, **who}
            r = await http.post(base + f"api/machines/{machine}/start", params=params,
                                ssl=ctx)
            body = await r.json()
            if r.status != 202:
                raise UserError(body.get("error", f"daemon answered HTTP {r.status}"))
            run_id = body["run_id"]
            with Progress(TextColumn("[bold]{task.fields[state]:<10}"), BarColumn(),
                          MofNCompleteColumn(), TextColumn("touches  {task.fields[eta]}"),
                          console=console, disable=quiet) as bar:
                task = bar.add_task(run_id, total=None, state="PREPARE", eta="")
                async def go_on() -> None:
                    await http.post(base + f"api/machines/{machine}/continue",
                                    params={"run_id": run_id, **who}, ssl=ctx)

                prompts = Prompts(console, go_on)
                follow = asyncio.create_task(follow_run(events, machine, run_id, bar, task,
                                                        prompts.see))
                stopping = asyncio.create_task(stop.wait())
                await asyncio.wait({follow, stopping}, return_when=asyncio.FIRST_COMPLETED)
                stopping.cancel()
                if stopped_by and not follow.done():
                    st = await abort_on_daemon(http, base, machine, run_id, stopped_by[0],
                                               follow, ctx)
                else:
                    st = await follow
                prompts.close()
            events.close()
    except aiohttp.ClientError as e:
        raise UserError(f"daemon at {base} unreachable: {e}") from None
    finally:
        _restore_signals()
    code = map_exit(run_id, st, console) if job == "map" else \
        _verdict_exit(run_id, st, strict, console)
    return 128 + int(stopped_by[0]) if stopped_by else code


def cmd_verify(args: argparse.Namespace) -> int:
    setup_terminal_logging(logging.WARNING, tracebacks=bool(os.environ.get("RUMBA_DEBUG")))
    operator = getattr(args, "operator", None)
    if operator is not None:  # the journal's and the report's rules for a person's name
        from daemon.compensation.names import BadName, validate_by

        try:
            validate_by(operator, "--operator", allow_unattended=False)
        except BadName as e:
            raise UserError(str(e)) from None
    job = "map" if getattr(args, "map", False) else "check"
    if args.daemon:
        return asyncio.run(verify_via_daemon(args.config, args.machine, strict=args.strict,
                                             quiet=args.quiet, operator=operator or "",
                                             job=job))
    return asyncio.run(verify(args.config, args.machine, strict=args.strict, quiet=args.quiet,
                              operator=operator or "", job=job))
