"""Link configuration schemas (pydantic, unknown keys are errors), one per transport."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator


class _Strict(BaseModel):
    # allow_inf_nan=False: .nan / .inf / 1e400 are refused in every float of this schema
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class SerialLinkConfig(_Strict):
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


class OpcUaUserConfig(_Strict):
    name: str = Field(min_length=1)
    password: str | None = None
    password_env: str | None = None  # name of an environment variable holding the password

    @model_validator(mode="after")
    def _one(self) -> OpcUaUserConfig:
        if (self.password is None) == (self.password_env is None):
            raise ValueError("give exactly one of 'password' or 'password_env'")
        return self

    def secret(self) -> str:
        if self.password is not None:
            return self.password
        value = os.environ.get(self.password_env or "")
        if value is None:
            raise ValueError(f"environment variable {self.password_env} (OPC UA password) unset")
        return value


class OpcUaLinkConfig(_Strict):
    """OPC UA client; node ids default to the rumba address space (drivers/README.md)."""

    transport: Literal["opcua"]
    url: str = Field(pattern=r"^opc\.tcp://")
    security: Literal["Basic256Sha256_SignAndEncrypt", "Basic256Sha256_Sign", "none"] = (
        "Basic256Sha256_SignAndEncrypt")
    certificate: Path | None = None  # our client certificate (DER or PEM)
    private_key: Path | None = None
    server_certificate: Path | None = None  # pin the server's certificate (recommended)
    application_uri: str = "urn:rumba-cnc:daemon"
    user: OpcUaUserConfig | None = None
    nodes: dict[str, str] = {}  # override node ids by role (see drivers/opcua.py NODE_ROLES)
    namespace_uri: str = "urn:rumba-cnc:cnc"
    connect_timeout_s: float = Field(15.0, gt=0)
    request_timeout_s: float = Field(10.0, gt=0)
    result_timeout_s: float = Field(300.0, gt=0)

    @model_validator(mode="after")
    def _certs(self) -> OpcUaLinkConfig:
        if self.security != "none" and (self.certificate is None or self.private_key is None):
            raise ValueError(f"security {self.security} needs 'certificate' and 'private_key'")
        return self


class ModbusLinkConfig(_Strict):
    """Modbus TCP client for the rumba register map (drivers/modbus_map.py)."""

    transport: Literal["modbus"]
    host: str = "127.0.0.1"
    port: int = Field(502, ge=1, le=65535)
    device_id: int = Field(1, ge=0, le=255)
    base_address: int = Field(0, ge=0, le=60000)  # shifts the whole map (PLC data area offset)
    poll_interval_s: float = Field(0.005, gt=0, le=1.0)
    request_timeout_s: float = Field(1.0, gt=0, le=30)  # per request (one retry follows)
    connect_timeout_s: float = Field(10.0, gt=0)
    block_timeout_s: float = Field(120.0, gt=0)  # mailbox block not acknowledged in this time
    result_timeout_s: float = Field(300.0, gt=0)


class LinuxCncLinkConfig(_Strict):
    """LinuxCNC: ``remote`` through linuxcncrsh (TCP) or ``local`` through the ``linuxcnc``
    Python module (daemon on the LinuxCNC PC); protocol in drivers/linuxcnc.py."""

    transport: Literal["linuxcnc"]
    mode: Literal["remote", "local"] = "remote"
    # how the program runs: "mdi" streams it block by block (remote and local); "auto" writes
    # it to a file on this PC and runs it in AUTO mode (local only; opt-in: LinuxCNC <= 2.9 can
    # stop an AUTO probing program with "Queue is not empty after probing", config/linuxcnc/)
    run: Literal["mdi", "auto"] = "mdi"
    # local auto: folder of the per-run program file (default: the system temp folder); the
    # LinuxCNC user must be able to read it
    program_dir: str | None = Field(None, pattern=r"^/[^\x00-\x1f]{0,200}$")
    host: str = "127.0.0.1"
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


class CanPanelConfig(_Strict):
    """Operator panel on a CAN bus (python-can interface + channel; frame map in can_panel.py)."""

    transport: Literal["can"] = "can"
    machine: str | None = None  # the machine its buttons act on (required with several)
    interface: str = "socketcan"
    channel: str = "can0"
    bitrate: int | None = Field(None, ge=10000, le=1000000)
    base_id: int = Field(0x640, ge=0, le=0x7F0)  # 11-bit ids base+0 .. base+2 (README)
    heartbeat_s: float = Field(1.0, gt=0, le=60)


LinkConfig = Annotated[SerialLinkConfig | OpcUaLinkConfig | ModbusLinkConfig | LinuxCncLinkConfig,
                       Field(discriminator="transport")]
