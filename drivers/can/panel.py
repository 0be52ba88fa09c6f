"""CAN operator panel (python-can): START / ABORT button frames in, status lamp frames out.

Frame map (11-bit identifiers from ``base_id``, default 0x640; table in drivers/README.md):
  base+0 BUTTON  panel → daemon  DLC 2: [button 1=START 2=ABORT, press counter 0-255]
  base+1 LAMP    daemon → panel  DLC 4: [lamp, progress % (255 = unknown), flags, alive counter]
  base+2 PANEL   panel → daemon  DLC 1: [alive counter] (optional panel heartbeat)
A button frame repeated with the same press counter is one press (retransmission, bounce).
The LAMP frame goes out on every change and every ``heartbeat_s``; a panel that misses it for
3 heartbeats should show "daemon lost".
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import AsyncIterator
from typing import Any

import can
from pydantic import ValidationError

from contracts.can_frames import (
    BUTTONS,
    LAMPS,
    OFFSET_BUTTON,
    OFFSET_PANEL,
    lamp_frame,
)
from drivers.can.schema import CanPanelConfig

log = logging.getLogger("rumba.can_panel")

FLAG_BLINK, FLAG_LINK_DOWN = 0x01, 0x02


def lamp_for(status: dict[str, Any]) -> tuple[str, int | None, int]:
    """Session status (daemon/run/session.py) → (lamp, progress %, flags)."""
    flags = 0 if status.get("link_ok", True) else FLAG_LINK_DOWN
    if status.get("busy"):
        total, done = status.get("total") or 0, status.get("done") or 0
        return "running", (100 * done // total) if total else None, flags | FLAG_BLINK
    state = str(status.get("state", "IDLE"))
    if state in ("FAILED", "ABORTED", "INTERRUPTED"):
        return "error", None, flags
    verdict = (status.get("verdict") or {}).get("status")
    lamp = {"PASS": "pass", "WARN": "warn", "FAIL": "fail", "ERROR": "error"}.get(verdict, "idle")
    return lamp, None, flags


class CanPanel:
    """The daemon's end of the panel bus."""

    def __init__(self, cfg: CanPanelConfig, bus: can.BusABC | None = None) -> None:
        self.cfg = cfg
        try:
            self.bus = bus or can.Bus(interface=cfg.interface, channel=cfg.channel,
                                      **({"bitrate": cfg.bitrate} if cfg.bitrate else {}))
        except (can.CanError, OSError, ValueError, ImportError) as e:
            raise OSError(f"can_panel: cannot open {cfg.interface} bus {cfg.channel!r}: "
                          f"{e}") from None
        self._reader = can.AsyncBufferedReader()
        self._notifier = can.Notifier(self.bus, [self._reader], timeout=0.05,
                                      loop=asyncio.get_running_loop())
        self._last_counter: int | None = None
        self.lamp: tuple[str, int | None, int] = ("idle", None, 0)
        self._alive = 0
        self.panel_seen_at: float | None = None
        self._heartbeat = asyncio.get_running_loop().create_task(self._beat())
        self._closed = False

    async def buttons(self) -> AsyncIterator[str]:
        """Yield "start" / "abort" once per press."""
        base = self.cfg.base_id
        while True:
            msg: can.Message = await self._reader.get_message()
            if msg.is_extended_id or msg.is_error_frame or msg.is_remote_frame:
                continue
            if msg.arbitration_id == base + OFFSET_PANEL:
                self.panel_seen_at = time.monotonic()
            if msg.arbitration_id != base + OFFSET_BUTTON or len(msg.data) < 2:
                continue
            button, counter = BUTTONS.get(msg.data[0]), msg.data[1]
            if button is None:
                log.warning("can_panel: unknown button code %d ignored", msg.data[0])
                continue
            if counter == self._last_counter:
                continue  # same press repeated
            self._last_counter = counter
            yield button

    def set_lamp(self, lamp: str, progress: int | None = None, flags: int = 0) -> None:
        if lamp not in LAMPS:
            raise ValueError(f"lamp {lamp!r}: expected one of {sorted(LAMPS)}")
        changed = (lamp, progress, flags) != self.lamp
        self.lamp = (lamp, progress, flags)
        if changed:
            self._send()

    def _send(self) -> None:
        self._alive = (self._alive + 1) & 0xFF
        try:
            self.bus.send(lamp_frame(self.cfg.base_id, *self.lamp, self._alive))
        except can.CanError as e:  # bus off / no panel: the run must go on
            log.warning("can_panel: lamp frame not sent: %s", e)

    async def _beat(self) -> None:
        while True:
            await asyncio.sleep(self.cfg.heartbeat_s)
            self._send()

    async def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._heartbeat.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._heartbeat
        self._notifier.stop()
        self.bus.shutdown()


class _Attached:
    """A panel wired to one session of the daemon service."""

    def __init__(self, panel: CanPanel, session: Any) -> None:
        self.panel, self.session = panel, session
        session.listeners.append(self._on_status)
        self._on_status(session.status())
        self._task = asyncio.get_running_loop().create_task(self._buttons())

    def _on_status(self, status: dict[str, Any]) -> None:
        self.panel.set_lamp(*lamp_for(status))

    async def _buttons(self) -> None:
        async for button in self.panel.buttons():
            try:
                if button == "start":
                    self.session.start("can")
                else:
                    await self.session.abort("CAN panel")
            except Exception as e:  # Refused (a run in progress, trigger disabled)
                log.warning("can_panel: %s refused: %s", button, e)

    async def close(self) -> None:
        self._task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._task
        with contextlib.suppress(ValueError):
            self.session.listeners.remove(self._on_status)
        await self.panel.close()


def attach(cfg: dict[str, Any], service: Any) -> _Attached:
    """Open the panel bus from the daemon's ``can_panel`` section and wire it to its machine."""
    from contracts.yaml_files import ConfigError, format_validation

    where = f"{service.config.path}: can_panel"
    try:
        pc = CanPanelConfig.model_validate(cfg)
    except ValidationError as e:
        raise ConfigError(format_validation(where, e)) from None
    names = sorted(service.sessions)
    name = pc.machine or (names[0] if len(names) == 1 else None)
    if name is None or name not in service.sessions:
        raise ConfigError(f"{where}: machine: expected one of {names}")
    try:
        panel = CanPanel(pc)
    except OSError as e:
        raise ConfigError(f"{where}: {e}") from None
    return _Attached(panel, service.sessions[name])
