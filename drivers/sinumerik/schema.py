"""The SINUMERIK OPC UA link's configuration schema (unknown keys are errors)."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator, model_validator

from contracts.sinumerik_space import BY_ROLE, NAMESPACE_URI, PROGRAM_NAME
from contracts.yaml_files import StrictModel
from drivers.opcua.schema import OpcUaUserConfig

NODE_ID = r"^ns=[0-9]{1,5};[isgb]=[^\x00-\x1f]{1,200}$"


class SinumerikLinkConfig(StrictModel):
    """The control's own OPC UA server (SINUMERIK Access MyMachine / OPC UA); node ids of the
    handshake default to R1-R5 of the channel (drivers/README.md), ``nodes:`` maps them onto the
    shop's R parameters or GUDs."""

    transport: Literal["sinumerik"]
    url: str = Field(pattern=r"^opc\.tcp://")
    security: Literal["Basic256Sha256_SignAndEncrypt", "Basic256Sha256_Sign", "none"] = (
        "Basic256Sha256_SignAndEncrypt")
    certificate: Path | None = None
    private_key: Path | None = None
    server_certificate: Path | None = None
    application_uri: str = "urn:rumba-cnc:daemon"
    user: OpcUaUserConfig | None = None
    namespace_uri: str = NAMESPACE_URI
    channel: int = Field(1, ge=1, le=10)
    program_name: str = "RUMBA"  # the part program's name: <NAME>.MPF in "Part Programs"
    # role → node id, e.g. {request: "ns=2;s=/NC/_N_NC_GD3_ACX/RUMBA_REQ"}
    nodes: dict[str, str] = Field(default_factory=dict)
    connect_timeout_s: float = Field(15.0, gt=0)
    request_timeout_s: float = Field(10.0, gt=0)
    result_timeout_s: float = Field(300.0, gt=0)
    nc_start_timeout_s: float = Field(900.0, gt=0)  # program selected → NC start at the machine
    stop_timeout_s: float = Field(8.0, gt=0)  # stop request → the program has ended

    @field_validator("program_name")
    @classmethod
    def _name(cls, v: str) -> str:
        if not PROGRAM_NAME.fullmatch(v):
            raise ValueError(f"{v!r}: a part-program name is an upper-case letter, then up to "
                             "23 upper-case letters, digits or '_'")
        return v

    @field_validator("nodes")
    @classmethod
    def _nodes(cls, v: dict[str, str]) -> dict[str, str]:
        import re

        unknown = sorted(set(v) - set(BY_ROLE))
        if unknown:
            raise ValueError(f"unknown role(s) {unknown} (known: {', '.join(BY_ROLE)})")
        bad = [f"{k}: {n!r}" for k, n in v.items() if not re.fullmatch(NODE_ID, n)]
        if bad:
            raise ValueError(f"not an OPC UA node id (ns=<index>;s=<path>): {', '.join(bad)}")
        return v

    @model_validator(mode="after")
    def _certs(self) -> SinumerikLinkConfig:
        if self.security != "none" and (self.certificate is None or self.private_key is None):
            raise ValueError(f"security {self.security} needs 'certificate' and 'private_key'")
        return self
