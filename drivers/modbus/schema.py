"""The Modbus TCP link's configuration schema (unknown keys are errors)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from contracts.yaml_files import HostName, StrictModel


class ModbusLinkConfig(StrictModel):
    """Modbus TCP client for the rumba register map (contracts/modbus_map.py): the gateway
    profile, a map a PLC or an edge box implements (no control ships it)."""

    transport: Literal["modbus"]
    profile: Literal["gateway"] = "gateway"  # the only one: said in the config, not assumed
    host: HostName = "127.0.0.1"
    port: int = Field(502, ge=1, le=65535)
    device_id: int = Field(1, ge=0, le=255)
    base_address: int = Field(0, ge=0, le=60000)  # shifts the whole map (PLC data area offset)
    poll_interval_s: float = Field(0.005, gt=0, le=1.0)
    request_timeout_s: float = Field(1.0, gt=0, le=30)  # per request (one retry follows)
    connect_timeout_s: float = Field(10.0, gt=0)
    block_timeout_s: float = Field(120.0, gt=0)  # mailbox block not acknowledged in this time
    result_timeout_s: float = Field(300.0, gt=0)
