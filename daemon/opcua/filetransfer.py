"""The report of a result through OPC 40001-101's ResultTransfer (a TemporaryFileTransferType,
OPC 10000-5 Annex C.4): GenerateFileForRead(ResultTransferOptions{ResultId}) makes a temporary
FileType object holding the run's PDF report (HTML when no PDF was made), opened for reading;
the client reads it with the file's Read and ends with its Close, which deletes the object."""

from __future__ import annotations

import contextlib
import secrets
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from asyncua import Server, ua

from daemon.opcua.source import ResultSource

FILE_TYPE = ua.NodeId(ua.ObjectIds.FileType)
MAX_READ = 1 << 20  # bytes per Read call (a client asking for more gets this much)
MAX_OPEN = 16  # temporary files at once per server: a client that never closes cannot pile up


@dataclass
class _Open:
    node: Any
    data: bytes
    pos: int = 0


async def report_file(source: ResultSource, run_id: str) -> Path | None:
    """The run's PDF report beside its HTML, else the HTML; None without a report (or when
    the fleet store names a file this host does not have)."""
    html = await source.report(run_id)
    if html is None:
        return None
    pdf = html.with_suffix(".pdf")
    return pdf if pdf.is_file() else (html if html.is_file() else None)


def _result_id(opts: Any) -> str | None:
    """ResultTransferOptionsDataType's ResultId. asyncua 2.1 does not register the decoder of a
    structure whose fields come from its base type, so the body may arrive undecoded: its only
    field is then read as OPC 10000-6 encodes a String (Int32 length + UTF-8)."""
    if isinstance(opts, ua.ExtensionObject):
        body = bytes(opts.Body or b"")
        if len(body) < 4:
            return None
        n = int.from_bytes(body[:4], "little", signed=True)
        if n < 0 or 4 + n != len(body):
            return None
        try:
            return body[4:].decode("utf-8")
        except UnicodeDecodeError:
            return None
    rid = getattr(opts, "ResultId", None)
    return rid if isinstance(rid, str) else None


class ResultTransfer:
    def __init__(self, server: Server, source: ResultSource, node: Any, ns: int) -> None:
        self.server, self.source, self.node, self.ns = server, source, node, ns
        self.open: dict[int, _Open] = {}

    async def bind(self) -> None:
        gen = await self.node.get_child(["0:GenerateFileForRead"])
        self.server.link_method(gen, self.generate)
        # results are read, never written by a client: the optional write methods are removed
        for name in ("0:GenerateFileForWrite", "0:CloseAndCommit"):
            with contextlib.suppress(ua.UaStatusCodeError):
                await self.server.delete_nodes([await self.node.get_child([name])])

    async def generate(self, parent: ua.NodeId, options: ua.Variant) -> list[ua.Variant]:
        run_id = _result_id(options.Value)
        if not isinstance(run_id, str):
            raise ua.UaStatusCodeError(ua.StatusCodes.BadInvalidArgument)
        try:
            path = await report_file(self.source, run_id)
        except Exception:  # an invalid run id
            path = None
        if path is None:
            raise ua.UaStatusCodeError(ua.StatusCodes.BadNotFound)
        if len(self.open) >= MAX_OPEN:
            raise ua.UaStatusCodeError(ua.StatusCodes.BadTooManyOperations)
        data = path.read_bytes()
        handle = secrets.randbits(31) or 1
        from asyncua.common.instantiate_util import instantiate

        name = f"{run_id}{path.suffix}"
        node = (await instantiate(self.node, self.server.get_node(FILE_TYPE),
                                    bname=ua.QualifiedName(name, self.ns), dname=ua.LocalizedText(
                                        name), idx=self.ns))[0]
        await (await node.get_child(["0:Size"])).write_value(ua.Variant(len(data),
                                                                         ua.VariantType.UInt64))
        await (await node.get_child(["0:OpenCount"])).write_value(ua.Variant(1,
                                                                             ua.VariantType.UInt16))
        await (await node.get_child(["0:Writable"])).write_value(False)
        await (await node.get_child(["0:UserWritable"])).write_value(False)
        mime = "application/pdf" if path.suffix == ".pdf" else "text/html"
        try:
            await (await node.get_child(["0:MimeType"])).write_value(mime)
        except ua.UaStatusCodeError:
            await node.add_property(self.ns, "MimeType", mime)
        self.server.link_method(await node.get_child(["0:Read"]), self.read)
        self.server.link_method(await node.get_child(["0:Close"]), self.close)
        self.server.link_method(await node.get_child(["0:GetPosition"]), self.get_position)
        self.server.link_method(await node.get_child(["0:SetPosition"]), self.set_position)
        self.server.link_method(await node.get_child(["0:Open"]), self.refuse_open)
        self.open[handle] = _Open(node, data)
        return [ua.Variant(node.nodeid, ua.VariantType.NodeId),
                ua.Variant(handle, ua.VariantType.UInt32),
                ua.Variant(ua.NodeId(), ua.VariantType.NodeId)]  # no completion state machine

    def _get(self, parent: ua.NodeId, handle: ua.Variant) -> _Open:
        f = self.open.get(int(handle.Value))
        if f is None or f.node.nodeid != parent:
            raise ua.UaStatusCodeError(ua.StatusCodes.BadInvalidArgument)
        return f

    async def read(self, parent: ua.NodeId, handle: ua.Variant,
                   length: ua.Variant) -> list[ua.Variant]:
        f = self._get(parent, handle)
        n = max(0, min(int(length.Value), MAX_READ))
        chunk = f.data[f.pos:f.pos + n]
        f.pos += len(chunk)
        return [ua.Variant(chunk, ua.VariantType.ByteString)]

    async def get_position(self, parent: ua.NodeId, handle: ua.Variant) -> list[ua.Variant]:
        return [ua.Variant(self._get(parent, handle).pos, ua.VariantType.UInt64)]

    async def set_position(self, parent: ua.NodeId, handle: ua.Variant,
                           pos: ua.Variant) -> list[ua.Variant]:
        f = self._get(parent, handle)
        f.pos = max(0, min(int(pos.Value), len(f.data)))
        return []

    async def refuse_open(self, parent: ua.NodeId, *args: Any) -> list[ua.Variant]:
        # the temporary file is opened by GenerateFileForRead; a second handle is not offered
        raise ua.UaStatusCodeError(ua.StatusCodes.BadNotWritable)

    async def close(self, parent: ua.NodeId, handle: ua.Variant) -> list[ua.Variant]:
        f = self._get(parent, handle)
        del self.open[int(handle.Value)]
        await self.server.delete_nodes([f.node], recursive=True)
        return []

    async def close_all(self) -> None:
        for h in list(self.open):
            f = self.open.pop(h)
            await self.server.delete_nodes([f.node], recursive=True)
