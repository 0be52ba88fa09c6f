"""Transport name → link class, and ``make_link(cfg)`` from a validated link config section.

Like python-can's interface registry: a dict of lazily imported classes, so a shop PC without
(say) a CAN stack never imports it.
"""

from __future__ import annotations

import importlib
from typing import Annotated, Any, get_args

from pydantic import BaseModel, Field, ValidationError

from contracts.jobs import DialectCodec
from drivers.base import CncLink
from drivers.haas.schema import HaasLinkConfig
from drivers.linuxcnc.schema import LinuxCncLinkConfig
from drivers.lsv2.schema import Lsv2LinkConfig
from drivers.modbus.schema import ModbusLinkConfig
from drivers.opcua.schema import OpcUaLinkConfig
from drivers.serial.schema import SerialLinkConfig
from drivers.sinumerik.schema import SinumerikLinkConfig

LinkConfig = Annotated[SerialLinkConfig | OpcUaLinkConfig | ModbusLinkConfig | LinuxCncLinkConfig
                       | SinumerikLinkConfig | Lsv2LinkConfig | HaasLinkConfig,
                       Field(discriminator="transport")]


TRANSPORTS: dict[str, tuple[str, str]] = {
    "serial": ("drivers.serial.link", "SerialDncLink"),
    "opcua": ("drivers.opcua.link", "OpcUaLink"),
    "modbus": ("drivers.modbus.link", "ModbusLink"),
    "linuxcnc": ("drivers.linuxcnc.link", "LinuxCncLink"),
    "sinumerik": ("drivers.sinumerik.link", "SinumerikLink"),
    "lsv2": ("drivers.lsv2.link", "Lsv2Link"),
    "haas": ("drivers.haas.link", "HaasLink"),
}
HANDSHAKE = frozenset({"sinumerik", "lsv2", "haas"})
"""Transports whose program carries the result handshake (``CncLink.handshake``: the link
reads the controller's variables), known without importing the link."""

_CONFIGS: dict[str, type[BaseModel]] = {
    get_args(m.model_fields["transport"].annotation)[0]: m
    for m in get_args(get_args(LinkConfig)[0])
}


def link_config(data: Any, where: str = "link") -> Any:
    """Validate a ``link:`` section (unknown keys are errors) → the transport's config model.

    Raises ``contracts.yaml_files.ConfigError`` with one line per problem, naming ``where``."""
    from contracts.yaml_files import ConfigError, format_validation

    if not isinstance(data, dict) or data.get("transport") not in TRANSPORTS:
        got = data.get("transport") if isinstance(data, dict) else type(data).__name__
        raise ConfigError(f"{where}: transport: expected one of {sorted(TRANSPORTS)}, got {got!r}")
    try:  # the transport's own model: error locations without the union's tag
        return _CONFIGS[data["transport"]].model_validate(data)
    except ValidationError as e:
        raise ConfigError(format_validation(where, e)) from None


def link_class(transport: str) -> type[CncLink]:
    module, name = TRANSPORTS[transport]
    return getattr(importlib.import_module(module), name)


def make_link(cfg: Any, dialect: DialectCodec | None = None, **kw: Any) -> CncLink:
    """The link object for a validated config (or a raw dict, validated first).

    ``dialect`` (the machine's, from the daemon) reaches the links that write G-code themselves
    (``CncLink.uses_dialect``); ``kw`` goes to the class, e.g. ``parse_result=`` for the serial
    link (default: the job's codec)."""
    if isinstance(cfg, dict):
        cfg = link_config(cfg)
    cls = link_class(cfg.transport)
    if dialect is not None and cls.uses_dialect:
        kw.setdefault("dialect", dialect)
    return cls(cfg, **kw)
