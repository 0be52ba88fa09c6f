"""The Haas data-port link's configuration schema (unknown keys are errors)."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator

from contracts.yaml_files import HostName, StrictModel

ROLES = ("request", "busy", "done", "program_ready")
DEFAULT_VARIABLES = {"request": 690, "busy": 691, "done": 692, "program_ready": 693}
"""Macro variables (legacy numbers) of the start-of-shift handshake, next to rumba's ring."""


class HaasLinkConfig(StrictModel):
    """A Haas NGC's Machine Data Collection port (Setting 143) for results, the handshake and
    the verdict; the program goes to the machine's network share (``program_dir``)."""

    transport: Literal["haas"]
    host: HostName
    port: int = Field(5051, ge=1, le=65535)  # Setting 143
    # NGC renumbered the user macro variables: legacy #600 is #10600 (0: a control that
    # answers for the legacy numbers)
    variable_base: Literal[0, 10000] = 10000
    variables: dict[str, int] = Field(default_factory=dict)  # role → legacy number
    program_dir: Path  # the share the machine reads programs from (O09100.nc is written there)
    request_timeout_s: float = Field(2.0, gt=0, le=30)
    connect_timeout_s: float = Field(15.0, gt=0)
    poll_interval_s: float = Field(0.1, gt=0, le=10)
    result_timeout_s: float = Field(300.0, gt=0)
    nc_start_timeout_s: float = Field(900.0, gt=0)
    stop_timeout_s: float = Field(8.0, gt=0)

    @field_validator("variables")
    @classmethod
    def _vars(cls, v: dict[str, int]) -> dict[str, int]:
        unknown = sorted(set(v) - set(ROLES))
        if unknown:
            raise ValueError(f"unknown role(s) {unknown} (known: {', '.join(ROLES)})")
        bad = [f"{k}: {n}" for k, n in v.items()
               if not (500 <= n <= 597 or 690 <= n <= 699 or 800 <= n <= 999)]
        if bad:
            raise ValueError(f"not a free common variable (#500-#597, #690-#699, #800-#999; "
                             f"#598-#689 are rumba's verdict, ring, ack and stop): "
                             f"{', '.join(bad)}")
        return v

    def variable(self, role: str) -> int:
        return self.variables.get(role, DEFAULT_VARIABLES[role])
