"""The daemon's fleet side, wired by the service: the drainer to the PostgreSQL fleet store
(``store.url``), one MQTT publisher per machine (``mqtt``) and the notifications (``notify``),
all optional and none able to block or fail a run."""

from __future__ import annotations

import asyncio
import contextlib
import json
import socket
from typing import Any

from daemon.config import DaemonConfig
from daemon.machines.setup import MachineSetup
from daemon.store.journal import Store


def limits_json(setup: MachineSetup) -> str:
    """The machine's numeric limits for the fleet trend: per link, and the defaults by unit."""
    t = setup.tolerances

    def lim(x: Any) -> dict[str, float | None] | None:
        return None if x is None else {"warn": x.warn, "fail": x.fail}

    return json.dumps({"links": {k: lim(v) for k, v in t.links.items()},
                       "default_um": lim(t.default_translation_um),
                       "default_urad": lim(t.default_rotation_urad)})


class FleetLink:
    def __init__(self, config: DaemonConfig, store: Store) -> None:
        """Before anything writes to the journal (the INTERRUPTED marks included), so the
        change capture sees every row."""
        self.config, self.store = config, store
        self.drainer: Any = None
        self.publishers: dict[str, Any] = {}
        self._health: asyncio.Task | None = None
        self.notifier: Any = None
        self._morning: asyncio.Task | None = None
        if config.store_dsn:
            from daemon.store.drain import Drainer

            self.drainer = Drainer(store, config.store_dsn,
                                   app=f"rumba@{socket.gethostname()}"[:63])
            site = config.mqtt.site if config.mqtt else ""
            self.drainer.declare_machines(
                (name, site, s.dialect, getattr(s.link, "transport", ""), limits_json(s))
                for name, s in config.machines.items())
            self.drainer.start()

    def attach(self, sessions: dict[str, Any]) -> None:
        """One publisher and one notification watcher per machine, listening to its
        session's status; the morning-check timer."""
        self._attach_notify(sessions)
        cfg = self.config.mqtt
        if cfg is None:
            return
        from daemon.mqtt.publisher import MachinePublisher

        for name, session in sessions.items():
            pub = MachinePublisher(cfg, name, self.store, self._daemon_health)
            session.listeners.append(pub.on_status)
            pub.on_status(session.status())
            pub.start()
            self.publishers[name] = pub
        self._health = asyncio.get_running_loop().create_task(self._health_loop(cfg),
                                                              name="mqtt-health")

    def _attach_notify(self, sessions: dict[str, Any]) -> None:
        cfg = self.config.notify
        if cfg is None:
            return
        from daemon.notify.notifier import Notifier, RunWatcher, morning_loop

        self.notifier = Notifier(cfg, self.config.mqtt.site if self.config.mqtt else "")
        for name, session in sessions.items():
            watcher = RunWatcher(self.notifier, name)
            session.listeners.append(watcher.on_status)
            watcher.on_status(session.status())
        if cfg.deadlines:
            self._morning = asyncio.get_running_loop().create_task(
                morning_loop(self.notifier, self.store,
                             lambda m: bool(sessions[m].busy) if m in sessions else False),
                name="notify-morning")

    def _daemon_health(self) -> dict[str, Any]:
        if self.drainer is None:
            return {}
        st = self.drainer.status()
        return {"fleet_store_connected": st["connected"],
                "fleet_store_backlog_rows": st["backlog_rows"]}

    async def _health_loop(self, cfg: Any) -> None:
        while True:
            await asyncio.sleep(cfg.health_interval_s)
            for pub in self.publishers.values():
                pub.publish_health()

    async def close(self) -> None:
        for task in (self._health, self._morning):
            if task is not None:
                task.cancel()
                with contextlib.suppress(BaseException):
                    await task
        if self.notifier is not None:
            await self.notifier.close()
        for pub in self.publishers.values():
            with contextlib.suppress(Exception):
                await pub.stop()
        if self.drainer is not None:
            with contextlib.suppress(Exception):
                await self.drainer.stop()
