"""The OPC UA link's configuration schema (unknown keys are errors)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

from pydantic import Field, model_validator

from contracts.yaml_files import StrictModel


class OpcUaUserConfig(StrictModel):
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


class OpcUaLinkConfig(StrictModel):
    """OPC UA client for the rumba address space (drivers/README.md): the gateway profile, a
    space a PLC or an edge box implements (a SINUMERIK's own server: ``transport: sinumerik``)."""

    transport: Literal["opcua"]
    profile: Literal["gateway"] = "gateway"  # the only one: said in the config, not assumed
    url: str = Field(pattern=r"^opc\.tcp://")
    security: Literal["Basic256Sha256_SignAndEncrypt", "Basic256Sha256_Sign", "none"] = (
        "Basic256Sha256_SignAndEncrypt")
    certificate: Path | None = None  # our client certificate (DER or PEM)
    private_key: Path | None = None
    server_certificate: Path | None = None  # pin the server's certificate (recommended)
    application_uri: str = "urn:rumba-cnc:daemon"
    user: OpcUaUserConfig | None = None
    # override node ids by role (see drivers/opcua/link.py NODE_ROLES)
    nodes: dict[str, str] = Field(default_factory=dict)
    namespace_uri: str = "urn:rumba-cnc:cnc"
    connect_timeout_s: float = Field(15.0, gt=0)
    request_timeout_s: float = Field(10.0, gt=0)
    result_timeout_s: float = Field(300.0, gt=0)

    @model_validator(mode="after")
    def _certs(self) -> OpcUaLinkConfig:
        if self.security != "none" and (self.certificate is None or self.private_key is None):
            raise ValueError(f"security {self.security} needs 'certificate' and 'private_key'")
        return self
