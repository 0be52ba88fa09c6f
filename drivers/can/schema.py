"""The CAN operator panel link's configuration schema (unknown keys are errors)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from contracts.yaml_files import StrictModel


class CanPanelConfig(StrictModel):
    """Operator panel on a CAN bus (python-can interface + channel; frame map in
    contracts/can_frames.py)."""

    transport: Literal["can"] = "can"
    machine: str | None = None  # the machine its buttons act on (required with several)
    interface: str = "socketcan"
    channel: str = "can0"
    bitrate: int | None = Field(None, ge=10000, le=1000000)
    base_id: int = Field(0x640, ge=0, le=0x7F0)  # 11-bit ids base+0 .. base+2 (README)
    heartbeat_s: float = Field(1.0, gt=0, le=60)
