"""``rumba run``: the asyncio service — one session per configured machine, its link, the
triggers (CNC start-of-shift request, HMI button, CAN panel button, ``rumba verify``) and the HMI.

Startup is strict (a bad config, an unreachable controller or a busy port is a one-line
``ServiceError``); afterwards a lost link is reconnected with backoff by its session and the
service keeps serving. Runs that a crash left half-done are marked INTERRUPTED, hits kept; a
run under way when the service stops ends INTERRUPTED too (``rerun_interrupted``).
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import ssl
from collections.abc import Callable
from pathlib import Path
from typing import Any

from aiohttp import web

from daemon.compensation.propose import journal_analyse
from daemon.config import DaemonConfig
from daemon.machines.setup import MachineSetup
from daemon.run.ending import cancel_until_done
from daemon.run.session import Refused, Session
from daemon.run.unattended import after_run
from daemon.service.fleet_link import FleetLink
from daemon.store import report_jobs
from daemon.store.journal import Store
from drivers.base import CncLink, LinkError

log = logging.getLogger("rumba.service")


class ServiceError(Exception):
    """The service cannot start; the message is one line naming the cause."""


LinkFactory = Callable[[MachineSetup], CncLink]


def make_link(setup: MachineSetup) -> CncLink:
    """The transport object for a machine's ``link`` section (drivers.registry)."""
    from drivers.registry import make_link as registry_link
    from programs.dialects import get_dialect

    return registry_link(setup.link, dialect=get_dialect(setup.dialect))


def _accounts(path: Path | None) -> Any:
    """The HMI accounts of ``hmi.users_file`` (``daemon.hmi.users.Accounts``), or None."""
    if path is None:
        return None
    from daemon.hmi.users import Accounts, UsersError

    try:
        return Accounts(path)
    except UsersError as e:
        raise ServiceError(f"hmi.users_file: {e}") from None


def _connect_timeout(setup: MachineSetup) -> float:
    return float(getattr(setup.link, "connect_timeout_s", 10.0))


class Service:
    def __init__(self, config: DaemonConfig, link_factory: LinkFactory = make_link,
                 **session_kw: Any) -> None:
        self.config = config
        self.link_factory = link_factory
        self.session_kw = session_kw  # e.g. prepare= for tests that replay a log
        self.store: Store | None = None
        self.sessions: dict[str, Session] = {}
        self.links: dict[str, CncLink] = {}
        self.interrupted: list[str] = []
        self.hmi_url: str | None = None
        self._runner: web.AppRunner | None = None
        self._tasks: list[asyncio.Task] = []
        self.panel: Any = None
        self.fleet: FleetLink | None = None
        self.opcua: Any = None  # daemon.opcua.server.ResultServer
        self.opcua_url: str | None = None
        self.aqdef: dict[str, Any] = {}  # machine -> daemon.service.aqdef_drop.AqdefDrop

    # ------------------------------------------------------------------------------ startup
    async def start(self) -> None:
        cfg = self.config
        self.store = Store(cfg.store_path, cfg.synchronous,  # type: ignore[arg-type]
                           source=f"{cfg.path}: store.path")
        self.fleet = FleetLink(cfg, self.store)  # fleet store drainer, MQTT (both optional)
        self.interrupted = self.store.mark_interrupted()
        for rid in self.interrupted:
            log.warning("run %s was interrupted (daemon stopped mid-run); hits kept", rid)
        for rid in report_jobs.mark_abandoned(self.store):
            log.warning("run %s: its report was being written when the daemon stopped; "
                        "journaled not written (the run and its verdict are kept)", rid)
        try:
            for name, setup in cfg.machines.items():
                link = self.link_factory(setup)
                self.links[name] = link
                try:
                    await asyncio.wait_for(link.connect(), _connect_timeout(setup) + 5.0)
                except (LinkError, OSError, TimeoutError) as e:
                    raise ServiceError(f"machine {name}: controller unreachable: "
                                       f"{str(e) or type(e).__name__}") from None
                if any(self.store.run(r).machine == name for r in self.interrupted):
                    await self._stop_leftover(name, link)
                # runs are identified against the model the controller holds
                kw = {"analyse": journal_analyse(cfg.store_path), "after_run": after_run,
                      **self.session_kw}
                self.sessions[name] = Session(setup, link, self.store, cfg.reports_dir, **kw)
            self.fleet.attach(self.sessions)
            await self._start_results()
            if cfg.hmi.enabled:
                await self._start_hmi()
            await self._start_panel()
        except BaseException:
            await self.stop()
            raise
        for name, session in self.sessions.items():
            setup = session.setup
            if setup.triggers.cnc and session.link.capabilities.start_request:
                self._tasks.append(asyncio.create_task(self._cnc_trigger(name),
                                                       name=f"cnc-trigger-{name}"))
            last = self.store.runs(name, limit=1)
            # INTERRUPTED: a crash (marked above), the daemon stopped under the run, a lost
            # link; never a run a person aborted or one that failed
            if setup.rerun_interrupted and last and last[0].state == "INTERRUPTED":
                log.info("%s: starting a new run after the interrupted one", name)
                session.start("rerun")

    async def _start_results(self) -> None:
        """The AQDEF drop and the OPC UA results server, both optional, both
        listening to the sessions' status (neither can block or fail a run)."""
        cfg = self.config
        if cfg.aqdef_dir is not None:
            from daemon.service.aqdef_drop import AqdefDrop

            for name, session in self.sessions.items():
                self.aqdef[name] = AqdefDrop(cfg.aqdef_dir, session.setup, self.store)
                session.listeners.append(self.aqdef[name].on_status)
        if cfg.opcua_server is None:
            return
        from contracts.yaml_files import ConfigError
        from daemon.opcua.server import OpcUaServerError, ResultServer

        self.opcua = ResultServer(cfg.opcua_server, self.store, list(self.sessions))
        try:
            self.opcua_url = await self.opcua.start()
        except (OpcUaServerError, ConfigError) as e:
            raise ServiceError(f"{cfg.path}: {e}") from None
        for name, session in self.sessions.items():
            listener = self.opcua.listener(name)
            session.listeners.append(listener)
            listener(session.status())
        log.info("OPC UA results server on %s", self.opcua_url)

    async def _stop_leftover(self, name: str, link: CncLink) -> None:
        """The controller may still run the interrupted program, whose results nobody reads
        any more: stop it, so the next run starts from a known state."""
        try:
            await asyncio.wait_for(link.abort(), 10.0)
            log.warning("%s: stopped the program left running by the interrupted run", name)
        except Exception as e:
            log.warning("%s: could not stop a leftover program: %s", name, e)

    async def _start_hmi(self) -> None:
        from contracts.yaml_files import ConfigError
        from daemon.hmi.app import create_app
        from daemon.hmi.auth import SECRET_FILE, SecretError, load_or_create_secret
        from daemon.hmi.tls import server_context
        from daemon.hosts import is_loopback

        cfg = self.config
        ctx: ssl.SSLContext | None = None
        if cfg.hmi_tls is not None:
            try:
                ctx = server_context(*cfg.hmi_tls, f"{cfg.path}: hmi.tls")
            except ConfigError as e:
                raise ServiceError(str(e)) from None
        elif not is_loopback(cfg.hmi.host):
            log.warning("%s: hmi: listening on %s without tls: the operator token and session "
                        "cookies cross the network in clear text; configure hmi.tls",
                        cfg.path, cfg.hmi.host)
        try:  # next to the journal: the state directory (StateDirectory= under systemd)
            secret = load_or_create_secret(cfg.store_path.parent / SECRET_FILE)
        except SecretError as e:
            raise ServiceError(str(e)) from None
        app = create_app(self.sessions, self.store, cfg.hmi_token or "",  # type: ignore[arg-type]
                         secure_cookie=ctx is not None, secret=secret,
                         bind_host=cfg.hmi.host, public_origins=cfg.hmi.public_origins,
                         stale_after_h=cfg.hmi.stale_after_h,
                         accounts=_accounts(cfg.users_file))
        self._runner = web.AppRunner(app, access_log=None, handle_signals=False)
        await self._runner.setup()
        site = web.TCPSite(self._runner, cfg.hmi.host, cfg.hmi.port, ssl_context=ctx)
        try:
            await site.start()
        except OSError as e:
            why = "address already in use" if e.errno == errno.EADDRINUSE else e.strerror
            raise ServiceError(f"{cfg.path}: hmi: cannot listen on {cfg.hmi.host}:"
                               f"{cfg.hmi.port}: {why}") from None
        port = site._server.sockets[0].getsockname()[1]  # type: ignore[union-attr]
        scheme = "https" if ctx else "http"
        self.hmi_url = f"{scheme}://{cfg.hmi.host}:{port}/"

    async def _start_panel(self) -> None:
        """The CAN operator panel: its button starts/aborts, its lamps show the state."""
        if not self.config.can_panel:
            return
        try:
            from drivers.can import panel as can_panel
        except ImportError as e:
            raise ServiceError(f"{self.config.path}: can_panel: driver unavailable: {e}") from None
        self.panel = can_panel.attach(self.config.can_panel, self)

    # ----------------------------------------------------------------------------- triggers
    def trigger(self, machine: str, source: str) -> str:
        """Start a run from ``source`` (hmi, can, cli …); raises Refused with the reason."""
        session = self.sessions.get(machine)
        if session is None:
            raise Refused(f"no machine {machine!r} (configured: {', '.join(self.sessions)})")
        return session.start(source)

    async def abort(self, machine: str, source: str) -> bool:
        session = self.sessions.get(machine)
        return bool(session and await session.abort(source))

    async def _cnc_trigger(self, name: str) -> None:
        """The CNC's start-of-shift request (``link.wait_start_request``) → ``session.start``."""
        session, link = self.sessions[name], self.links[name]
        while True:
            try:
                req = await link.wait_start_request()
            except asyncio.CancelledError:
                raise
            except Exception as e:
                log.warning("%s: waiting for the start request failed: %s", name, e)
                session.set_link_ok(False)
                await session.reconnect()
                continue
            try:
                run_id = session.start("cnc")
                log.info("%s: start-of-shift request %s → run %s", name, req.detail, run_id)
            except Refused as e:
                log.warning("%s", e)
            await session.wait()

    # ----------------------------------------------------------------------------- shutdown
    async def stop(self) -> None:
        for t in self._tasks:
            t.cancel()
        for t in self._tasks:  # cancelled again if a Modbus read swallowed it (cancel_until_done)
            await cancel_until_done(t)
            with contextlib.suppress(BaseException):
                await t
        # every machine's run and report at once: their bounded waits do not add up within
        # systemd's stop timeout (config/systemd/rumba.service: TimeoutStopSec=30s)
        await asyncio.gather(*(s.shutdown("the daemon stopping")  # its report: finished/failed
                               for s in self.sessions.values()), return_exceptions=True)
        if self.panel is not None:
            with contextlib.suppress(Exception):
                await self.panel.close()
        if self._runner is not None:
            await self._runner.cleanup()
        for link in self.links.values():
            with contextlib.suppress(Exception):
                await link.close()
        if self.opcua is not None:
            with contextlib.suppress(Exception):
                await self.opcua.stop()
        if self.fleet is not None:
            await self.fleet.close()
        if self.store is not None:
            self.store.close()
