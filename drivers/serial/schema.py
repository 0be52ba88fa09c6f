"""The serial DNC link's configuration schema (unknown keys are errors)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from contracts.yaml_files import StrictModel


class SerialLinkConfig(StrictModel):
    """RS-232 DNC drip-feed (``url``: a device path, ``socket://host:port`` or ``rfc2217://…``)."""

    transport: Literal["serial"]
    url: str = Field(min_length=1)
    baudrate: int = Field(9600, ge=300, le=921600)
    framing: Literal["7E1", "8N1", "7E2", "8N2"] = "7E1"
    eol: Literal["LF", "CRLF"] = "LF"
    xonxoff: bool = True
    # bytes in flight at most (written but not yet on the line): set it at or below the
    # control's slack above its XOFF high-water mark
    tx_chunk_bytes: int = Field(16, ge=1, le=256)
    # start-request lines within this time after a run's end are refused (echoes of the
    # request just served, not a new start of shift)
    request_holdoff_s: float = Field(5.0, ge=0, le=3600)
    xoff_timeout_s: float = Field(120.0, gt=0)  # XOFF held longer than this → link error
    result_timeout_s: float = Field(300.0, gt=0)  # no result line for this long after the end
    connect_timeout_s: float = Field(10.0, gt=0)
    # Start-of-shift request lines naming another machine are ignored (None: any name).
    request_machine: str | None = Field(None, pattern=r"^[A-Za-z0-9_.-]{1,32}$")
