"""The LSV2 link's configuration schema (unknown keys are errors)."""

from __future__ import annotations

import re
from typing import Literal

from pydantic import Field, field_validator

from contracts.yaml_files import HostName, StrictModel

TNC_DIR = re.compile(r"^TNC:(\\[A-Z0-9_]{1,16}){1,4}$")


class Lsv2LinkConfig(StrictModel):
    """A HEIDENHAIN TNC (iTNC 530, TNC 320/620/640, TNC7 while it has LSV2) over LSV2, port
    19000; results from the FN 16 file the program writes next to itself (drivers/README.md)."""

    transport: Literal["lsv2"]
    host: HostName
    port: int = Field(19000, ge=1, le=65535)
    directory: str = "TNC:\\RUMBA"  # the program, its format files, stop and verdict programs
    request_machine: str | None = Field(None, pattern=r"^[A-Za-z0-9_.-]{1,32}$")
    timeout_s: float = Field(15.0, gt=0, le=120)  # one LSV2 telegram's answer
    connect_timeout_s: float = Field(15.0, gt=0)
    poll_interval_s: float = Field(0.5, gt=0, le=10)
    result_timeout_s: float = Field(300.0, gt=0)
    nc_start_timeout_s: float = Field(900.0, gt=0)  # program transferred → NC start there
    stop_timeout_s: float = Field(60.0, gt=0)  # stop program written → the program has ended

    @field_validator("directory")
    @classmethod
    def _dir(cls, v: str) -> str:
        if not TNC_DIR.fullmatch(v):
            raise ValueError(f"{v!r}: a folder on the TNC drive, TNC:\\<NAME>[\\<NAME>…] with "
                             "upper-case letters, digits and '_'")
        return v
