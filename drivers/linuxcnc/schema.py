"""The LinuxCNC link's configuration schema (unknown keys are errors)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, model_validator

from contracts.yaml_files import HostName, StrictModel


class LinuxCncLinkConfig(StrictModel):
    """LinuxCNC: ``remote`` through linuxcncrsh (TCP) or ``local`` through the ``linuxcnc``
    Python module (daemon on the LinuxCNC PC); protocol in drivers/linuxcnc/link.py."""

    transport: Literal["linuxcnc"]
    mode: Literal["remote", "local"] = "remote"
    # how the program runs: "mdi" streams it block by block (remote and local); "auto" writes
    # it to a file on this PC and runs it in AUTO mode (local only; opt-in: LinuxCNC <= 2.9 can
    # stop an AUTO probing program with "Queue is not empty after probing", config/linuxcnc/)
    run: Literal["mdi", "auto"] = "mdi"
    # local auto: folder of the per-run program file (default: the system temp folder); the
    # LinuxCNC user must be able to read it
    program_dir: str | None = Field(None, pattern=r"^/[^\x00-\x1f]{0,200}$")
    host: HostName = "127.0.0.1"
    port: int = Field(5007, ge=1, le=65535)  # linuxcncrsh --port
    hello_password: str = Field("EMC", pattern=r"^[A-Za-z0-9_.-]{1,64}$")
    enable_password: str = Field("EMCTOO", pattern=r"^[A-Za-z0-9_.-]{1,64}$")
    client_name: str = Field("rumba", pattern=r"^[A-Za-z0-9_.-]{1,32}$")
    helper_python: str = "/usr/bin/python3"  # local mode: the interpreter with `linuxcnc`
    local_home: str | None = None  # local mode: HOME of the LinuxCNC user, if not the daemon's
    joints: int = Field(5, ge=1, le=9)
    home_if_needed: bool = True  # home all joints (set home -1) when not homed
    # MDI lines sent before every program, e.g. ["M429"] (joint space on a switchkins machine)
    # or ["T1 M6 G43"]; letters, digits, spaces and . # = [ ] + - only (no comments).
    prelude_mdi: list[Annotated[str, Field(pattern=r"^[A-Za-z0-9 .#=\[\]+-]{1,120}$")]] = []
    verdict_output: int = Field(0, ge=0, le=63)  # M68 E<n>: motion.analog-out-<n>
    count_output: int = Field(1, ge=0, le=63)
    connect_timeout_s: float = Field(10.0, gt=0)
    command_timeout_s: float = Field(120.0, gt=0)  # longest single block (a long rapid)
    poll_interval_s: float = Field(0.005, gt=0, le=1.0)  # operator_display while a touch runs

    @model_validator(mode="after")
    def _run_mode(self) -> LinuxCncLinkConfig:
        if self.run == "auto" and self.mode == "remote":
            raise ValueError("run: auto needs mode: local (the program file is written on the "
                             "LinuxCNC PC; linuxcncrsh has no upload) — use run: mdi remotely")
        return self
