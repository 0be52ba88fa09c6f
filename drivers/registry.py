"""Transport name → link class, and ``make_link(cfg)`` from a validated link config section.

Like python-can's interface registry: a dict of lazily imported classes, so a shop PC without
(say) a CAN stack never imports it.
"""

from __future__ import annotations

import importlib
from typing import Any, get_args

from pydantic import BaseModel, ValidationError

from drivers.base import CncLink, DialectCodec
from drivers.link_config import LinkConfig

TRANSPORTS: dict[str, tuple[str, str]] = {
    "serial": ("drivers.serial_dnc", "SerialDncLink"),
    "opcua": ("drivers.opcua", "OpcUaLink"),
    "modbus": ("drivers.modbus", "ModbusLink"),
    "linuxcnc": ("drivers.linuxcnc", "LinuxCncLink"),
}

_CONFIGS: dict[str, type[BaseModel]] = {
    get_args(m.model_fields["transport"].annotation)[0]: m
    for m in get_args(get_args(LinkConfig)[0])
}


def link_config(data: Any, where: str = "link") -> Any:
    """Validate a ``link:`` section (unknown keys are errors) → the transport's config model.

    Raises ``daemon.config.ConfigError`` with one line per problem, naming ``where``."""
    from daemon.config import ConfigError, format_validation

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
