"""The CAN operator panel's frames (ids, buttons, lamps), shared by the panel link and the
simulated panel."""

from __future__ import annotations

import can

BUTTONS = {1: "start", 2: "abort"}


BUTTON_CODES = {v: k for k, v in BUTTONS.items()}


LAMPS = {"off": 0, "idle": 1, "running": 2, "pass": 3, "warn": 4, "fail": 5, "error": 6}


LAMP_NAMES = {v: k for k, v in LAMPS.items()}


PROGRESS_UNKNOWN = 255


OFFSET_BUTTON, OFFSET_LAMP, OFFSET_PANEL = 0, 1, 2


def lamp_frame(base_id: int, lamp: str, progress: int | None, flags: int, alive: int
               ) -> can.Message:
    pct = PROGRESS_UNKNOWN if progress is None else max(0, min(100, int(progress)))
    return can.Message(arbitration_id=base_id + OFFSET_LAMP, is_extended_id=False,
                       data=bytes([LAMPS[lamp], pct, flags & 0xFF, alive & 0xFF]))


def button_frame(base_id: int, button: str, counter: int) -> can.Message:
    return can.Message(arbitration_id=base_id + OFFSET_BUTTON, is_extended_id=False,
                       data=bytes([BUTTON_CODES[button], counter & 0xFF]))
