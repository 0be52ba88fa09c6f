"""The OPC UA side of the SINUMERIK link: the secured session (Basic256Sha256 and user/password,
asyncua's reconnection), nodes by role, browsing by display name, method calls typed from the
method's own InputArguments, and the part program written through the server's file system
(OPC UA Part 5 Annex C: FileDirectoryType.CreateFile, FileType.Open / Write / Close). Reads,
writes and calls are awaited through ``drivers.cancel.keep_cancel``, as the gateway link's.
"""

from __future__ import annotations

import contextlib
import logging
import math
from typing import Any

from asyncua import Client, ua
from asyncua.client.ua_file_transfer import UaDirectory, UaFile

from contracts.sinumerik_space import (
    BY_ROLE,
    OPEN_ERASE,
    OPEN_WRITE,
    r_node,
    role_path,
)
from drivers.base import LinkError
from drivers.cancel import keep_cancel
from drivers.opcua_client import secure_client
from drivers.retry import Refused
from drivers.sinumerik.schema import SinumerikLinkConfig

logging.getLogger("asyncua").setLevel(logging.ERROR)
CHUNK_BYTES = 16 * 1024  # one Write call; well below any server's MaxByteStringLength


class Fatal(LinkError):
    """A connect failure retrying cannot fix (bad password, untrusted certificate)."""


def status_name(e: BaseException) -> str:
    """The OPC UA status of a failed service, by name (BadInvalidState …), else the error."""
    if isinstance(e, ua.UaStatusCodeError):
        return type(e).__name__  # asyncua raises the status's own class (BadInvalidState …)
    return str(e) or type(e).__name__


class SinumerikSession:
    """One connected session to the control's server, with its nodes resolved."""

    def __init__(self, cfg: SinumerikLinkConfig) -> None:
        self.cfg = cfg
        self.client: Client | None = None
        self.ns = 0

    async def open(self) -> None:
        """Connect once; ``Refused``/``LinkError`` when unreachable, ``Fatal`` when refused."""
        cfg = self.cfg
        try:
            client = await secure_client(cfg)
        except (OSError, ValueError) as e:
            raise Fatal(f"sinumerik {cfg.url}: security setup: {e}") from None
        try:
            await client.connect(auto_reconnect=True, reconnect_max_delay=10.0,
                                 reconnect_request_timeout=cfg.request_timeout_s)
        except ua.UaError as e:
            with contextlib.suppress(Exception):
                await client.disconnect()
            raise Fatal(f"sinumerik {cfg.url}: rejected: {type(e).__name__} ({e})") from None
        except (TimeoutError, OSError, ConnectionError) as e:
            with contextlib.suppress(Exception):
                await client.disconnect()
            error = Refused if isinstance(e, ConnectionRefusedError) else LinkError
            raise error(str(e) or type(e).__name__) from None
        try:
            self.ns = await client.get_namespace_index(cfg.namespace_uri)
        except (ua.UaError, ValueError) as e:
            with contextlib.suppress(Exception):
                await client.disconnect()
            raise Fatal(f"sinumerik {cfg.url}: no namespace {cfg.namespace_uri!r} on this "
                        f"server ({e}): not a SINUMERIK OPC UA server, or set namespace_uri"
                        ) from None
        self.client = client

    async def close(self) -> None:
        client, self.client = self.client, None
        if client is not None:
            with contextlib.suppress(Exception):
                await client.disconnect()

    # ------------------------------------------------------------------ nodes
    def _client(self) -> Client:
        if self.client is None:
            raise LinkError(f"sinumerik {self.cfg.url}: not connected")
        return self.client

    def node_id(self, role: str) -> str:
        """The node id of a role: the config's, else the profile's default in the channel."""
        return self.cfg.nodes.get(role) or f"ns={self.ns};s={role_path(role, self.cfg.channel)}"

    def role(self, role: str) -> Any:
        return self._client().get_node(self.node_id(role))

    def r_param(self, n: int) -> Any:
        return self._client().get_node(f"ns={self.ns};s={r_node(n, self.cfg.channel)}")

    async def read(self, nodes: list[Any], what: str) -> list[Any]:
        try:
            return await keep_cancel(self._client().read_values(nodes))
        except (TimeoutError, ua.UaError, OSError, ConnectionError) as e:
            raise LinkError(f"sinumerik {self.cfg.url}: read {what}: {status_name(e)}") from None

    async def write_double(self, node: Any, value: float, what: str) -> None:
        try:
            await keep_cancel(node.write_value(
                ua.DataValue(ua.Variant(float(value), ua.VariantType.Double))))
        except (TimeoutError, ua.UaError, OSError, ConnectionError) as e:
            raise LinkError(f"sinumerik {self.cfg.url}: write {what} = {value:g}: "
                            f"{status_name(e)}") from None

    async def check_roles(self, roles: tuple[str, ...]) -> None:
        """Every role's node answers (a typo, an R parameter beyond MD28050 or an undeclared
        GUD fails at connect, naming the role and the node)."""
        for role in roles:
            try:
                await self.role(role).read_value()
            except (ua.UaError, ValueError) as e:
                raise LinkError(f"sinumerik {self.cfg.url}: {role} = {self.node_id(role)} "
                                f"({BY_ROLE[role].doc.split(':')[0]}): {status_name(e)}") from None

    async def browse(self, *names: str) -> Any:
        """The node at ``Objects/<names…>`` matching display names (namespace indices are the
        server's); ``LinkError`` naming the first missing step."""
        node = self._client().nodes.objects
        for i, name in enumerate(names):
            try:
                found = None
                for child in await node.get_children():
                    if (await child.read_browse_name()).Name == name:
                        found = child
                        break
            except (ua.UaError, OSError, ConnectionError) as e:
                raise LinkError(f"sinumerik {self.cfg.url}: browse {'/'.join(names[:i + 1])}: "
                                f"{status_name(e)}") from None
            if found is None:
                raise LinkError(f"sinumerik {self.cfg.url}: no {'/'.join(names[:i + 1])} in "
                                "the server's address space (option or user rights missing?)")
            node = found
        return node

    async def call(self, parent: Any, method: Any, values: tuple[Any, ...], what: str) -> Any:
        """Call ``method`` with ``values`` typed as its InputArguments declare them (the
        number of arguments must agree: a server of another edition is refused, not guessed)."""
        try:
            args = await (await method.get_child("0:InputArguments")).read_value()
        except (ua.UaError, OSError, ConnectionError):
            args = []
        if len(args) != len(values):
            raise LinkError(f"sinumerik {self.cfg.url}: {what} declares {len(args)} input "
                            f"argument(s), rumba passes {len(values)}: another server edition "
                            "(drivers/README.md)")
        variants = []
        for arg, value in zip(args, values, strict=True):
            dtype = arg.DataType.Identifier if arg.DataType.NamespaceIndex == 0 else None
            vtype = ua.VariantType(dtype) if dtype in ua.VariantType._value2member_map_ else None
            if vtype is None:
                raise LinkError(f"sinumerik {self.cfg.url}: {what}: argument {arg.Name} of "
                                f"type {arg.DataType} not supported")
            variants.append(ua.Variant(value, vtype))
        try:
            return await keep_cancel(parent.call_method(method, *variants))
        except (TimeoutError, ua.UaError, OSError, ConnectionError) as e:
            raise LinkError(f"sinumerik {self.cfg.url}: {what} refused: {status_name(e)}"
                            ) from None

    async def upload(self, folder: Any, name: str, text: str) -> None:
        """``text`` as file ``name`` in ``folder`` (a FileDirectoryType): a file of that name
        is overwritten (Open with write | erase existing), else CreateFile; then Write in
        chunks and Close (the control takes the program at Close)."""
        try:
            data = text.encode("ascii")
        except UnicodeEncodeError as e:
            raise LinkError(f"program {name}: character {text[e.start]!r} at offset {e.start} "
                            "is not ASCII: not written to the control") from None
        where = f"sinumerik {self.cfg.url}: {name}"
        directory = UaDirectory(folder)
        try:
            node_id = None
            for child in await folder.get_children():
                if (await child.read_browse_name()).Name.upper() == name.upper():
                    node_id = child.nodeid
            if node_id is None:
                node_id, _ = await directory.create_file(name, False)
            async with UaFile(self._client().get_node(node_id), OPEN_WRITE | OPEN_ERASE) as f:
                for i in range(0, len(data), CHUNK_BYTES):
                    await f.write(data[i:i + CHUNK_BYTES])
        except (TimeoutError, ua.UaError, OSError, ConnectionError) as e:
            raise LinkError(f"{where}: not written ({status_name(e)})") from None


def finite(value: Any) -> float | None:
    """A finite number as float, else None (a Double node may hold NaN or a wrong type)."""
    if isinstance(value, int | float) and not isinstance(value, bool):
        with contextlib.suppress(OverflowError):
            if math.isfinite(value):
                return float(value)
    return None
