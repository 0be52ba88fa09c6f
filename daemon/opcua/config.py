"""The ``opcua_server`` section of daemon.yaml (off when absent): listen address, the server's
certificate folder, the trusted client certificates, users and their password files, where the
official nodesets are, and each machine's OPC 40001-1 identification."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from pydantic import Field, field_validator, model_validator

from contracts.setup_types import Record
from contracts.yaml_files import ConfigError, HostName, StrictModel
from daemon.hosts import is_loopback
from daemon.machines.setup import resolve_path

NODESETS = ("Opc.Ua.Di.NodeSet2.xml", "Opc.Ua.IA.NodeSet2.xml", "Opc.Ua.Machinery.NodeSet2.xml",
            "Opc.Ua.Machinery_Result.NodeSet2.xml")
"""The official nodesets loaded, in dependency order (DI, IA before Machinery; Result alone)."""


class IdentificationFile(StrictModel):
    """OPC 40001-1 MachineIdentificationType: the mandatory Manufacturer, SerialNumber and
    ProductInstanceUri (made from them when not given), and what a shop usually fills in."""

    manufacturer: Record
    model: Record | None = None
    serial_number: Record
    product_instance_uri: Record | None = None
    year_of_construction: int | None = Field(None, ge=1900, le=2200)
    location: Record | None = None


class OpcUaServerFile(StrictModel):
    host: HostName = "127.0.0.1"
    port: int = Field(4850, ge=0, le=65535)  # 0 = any free port (tests)
    allow_remote: bool = False  # must be true to bind anything but loopback
    cert_dir: str = "opcua-server"  # the server's certificate and key (made at first start)
    trusted_dir: str  # the trust list: a folder of admitted client certificates (.der / .pem)
    users: dict[str, str] = Field(min_length=1)  # user name -> password file (mode 600)
    nodesets_dir: str  # the official companion nodesets (node-opcua-nodesets' nodesets/)
    machines: dict[str, IdentificationFile] = {}

    @field_validator("users")
    @classmethod
    def _names(cls, v: dict[str, str]) -> dict[str, str]:
        bad = [u for u in v if not u or not u.isprintable() or len(u) > 64]
        if bad:
            raise ValueError(f"user names {bad}: 1-64 printable characters")
        return v

    @model_validator(mode="after")
    def _remote(self) -> OpcUaServerFile:
        if not is_loopback(self.host) and not self.allow_remote:
            raise ValueError(f"host {self.host} is not loopback; set allow_remote: true to "
                             "serve results on the network")
        return self


@dataclass(frozen=True)
class OpcUaServerConfig:
    host: str
    port: int
    cert_dir: Path
    trusted_dir: Path
    users: dict[str, str]  # name -> password
    nodesets: tuple[Path, ...]
    identification: dict[str, IdentificationFile]


def load_opcua_server(f: OpcUaServerFile, base: Path, where: str, machines: list[str],
                      read_secret: Callable[[Path, str], str]) -> OpcUaServerConfig:
    """Files checked now (one line naming the key), so the service starts or says why."""
    unknown = sorted(set(f.machines) - set(machines))
    if unknown:
        raise ConfigError(f"{where}.machines: {unknown} not configured machines "
                          f"({', '.join(machines)})")
    trusted = resolve_path(base, f.trusted_dir)
    if not trusted.is_dir() or not any(p.suffix.lower() in (".der", ".pem")
                                       for p in trusted.iterdir()):
        raise ConfigError(f"{where}.trusted_dir: {trusted} is not a folder holding client "
                          "certificates (.der or .pem): no client could connect")
    nodesets_dir = resolve_path(base, f.nodesets_dir)
    nodesets = tuple(nodesets_dir / n for n in NODESETS)
    missing = [n.name for n in nodesets if not n.is_file()]
    if missing:
        raise ConfigError(f"{where}.nodesets_dir: {nodesets_dir} lacks {', '.join(missing)} "
                          "(bash .ci/install-peers.sh node-opcua installs them)")
    users = {u: read_secret(resolve_path(base, p), f"{where}.users.{u}")
             for u, p in f.users.items()}
    return OpcUaServerConfig(f.host, f.port, resolve_path(base, f.cert_dir), trusted,
                             users, nodesets, dict(f.machines))
