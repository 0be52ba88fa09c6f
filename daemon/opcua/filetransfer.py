"""The report of a result through OPC 40001-101's ResultTransfer (a TemporaryFileTransferType,
OPC 10000-5 Annex C.4): GenerateFileForRead(ResultTransferOptions{ResultId}) makes a temporary
FileType object holding the run's PDF report (HTML when no PDF was made), opened for reading;
the client reads it with the file's Read and ends with its Close, which deletes the object.

A file belongs to the session that generated it (its handle is refused to any other); a
session closed without Close (a client gone, its session ended by the server) has its files
released within ``SWEEP_S``, a file not read for ``IDLE_S`` is released whatever its session
does, and a session holds at most ``MAX_PER_SESSION`` at once (``MAX_OPEN`` for the server)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import secrets
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from asyncua import Server, ua
from asyncua.common.instantiate_util import instantiate
from asyncua.common.manage_nodes import delete_nodes
from asyncua.server.internal_session import SessionState

from contracts.opcua_security import CHANNEL
from daemon.opcua.methods import Arg, method
from daemon.opcua.source import ResultSource

log = logging.getLogger("rumba.opcua")

FILE_TYPE = ua.NodeId(ua.ObjectIds.FileType)
MAX_READ = 1 << 20  # bytes per Read call (a client asking for more gets this much)
MAX_OPEN = 16  # temporary files at once per server: a client that never closes cannot pile up
MAX_PER_SESSION = 4
IDLE_S = 300.0  # a file not read for this long is released
SWEEP_S = 2.0  # how often files of closed sessions and idle files are looked for
HANDLE = Arg("FileHandle", "count")


@dataclass
class _Open:
    node: Any
    data: bytes
    session: Any  # asyncua's InternalSession that generated it (None: an in-process call)
    used: float = field(default_factory=time.monotonic)
    pos: int = 0


def _session() -> Any:
    channel = CHANNEL.get()
    return getattr(channel, "session", None)


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
        self.released = 0  # files released without their Close (session gone, idle)
        self._sweeper: asyncio.Task | None = None

    async def bind(self) -> None:
        gen = await self.node.get_child(["0:GenerateFileForRead"])
        self.server.link_method(gen, self.generate)
        # results are read, never written by a client: the optional write methods are removed
        for name in ("0:GenerateFileForWrite", "0:CloseAndCommit"):
            with contextlib.suppress(ua.UaStatusCodeError):
                await self.server.delete_nodes([await self.node.get_child([name])])
        self._sweeper = asyncio.create_task(self._sweep_loop(), name="opcua-file-sweep")

    async def _sweep_loop(self) -> None:
        while True:
            await asyncio.sleep(SWEEP_S)
            try:
                await self.sweep()
            except asyncio.CancelledError:
                raise
            except Exception as e:  # the address space refusing a delete: next round
                log.warning("OPC UA result files: release failed: %s", e)

    async def sweep(self, now: float | None = None) -> int:
        """Release the files whose session has closed or that were not read for ``IDLE_S``;
        return how many."""
        now = time.monotonic() if now is None else now
        gone = [h for h, f in self.open.items()
                if now - f.used > IDLE_S
                or (f.session is not None and f.session.state == SessionState.Closed)]
        for h in gone:
            f = self.open.pop(h, None)
            if f is not None:
                self.released += 1
                await self._delete(f.node)
        return len(gone)

    @method("GenerateFileForRead", Arg("GenerateOptions", "object"))
    async def generate(self, parent: ua.NodeId, options: Any) -> list[ua.Variant]:
        run_id = _result_id(options)
        if not isinstance(run_id, str):
            raise ua.UaStatusCodeError(ua.StatusCodes.BadInvalidArgument)
        try:
            path = await report_file(self.source, run_id)
        except Exception:  # an invalid run id
            path = None
        if path is None:
            raise ua.UaStatusCodeError(ua.StatusCodes.BadNotFound)
        await self.sweep()
        session = _session()
        if len(self.open) >= MAX_OPEN or sum(
                f.session is session for f in self.open.values()) >= MAX_PER_SESSION:
            raise ua.UaStatusCodeError(ua.StatusCodes.BadTooManyOperations)
        data = await asyncio.to_thread(path.read_bytes)
        handle = secrets.randbits(31) or 1
        while handle in self.open:
            handle = secrets.randbits(31) or 1
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
        self.open[handle] = _Open(node, data, session)
        return [ua.Variant(node.nodeid, ua.VariantType.NodeId),
                ua.Variant(handle, ua.VariantType.UInt32),
                ua.Variant(ua.NodeId(), ua.VariantType.NodeId)]  # no completion state machine

    async def _delete(self, node: Any) -> None:
        """Remove a temporary file object and its children. asyncua's ``delete_nodes`` also
        looks through every reference of every node of the address space for each node
        deleted (0.5 s per file with the Machinery nodesets, on the loop); a file object is
        referenced only by its parent and its own children, so that one reference is removed
        here and the subtree deleted without the search."""
        for ref in await node.get_references(direction=ua.BrowseDirection.Inverse):
            if ref.NodeId == self.node.nodeid:
                await self.node.delete_reference(node.nodeid, ref.ReferenceTypeId)
        await delete_nodes(self.server.iserver.isession, [node], recursive=True,
                           delete_target_references=False)

    def _get(self, parent: ua.NodeId, handle: int) -> _Open:
        """The open file ``handle`` of this file node and of the calling session."""
        f = self.open.get(handle)
        if f is None or f.node.nodeid != parent or f.session is not _session():
            raise ua.UaStatusCodeError(ua.StatusCodes.BadInvalidArgument)
        f.used = time.monotonic()
        return f

    @method("Read", HANDLE, Arg("Length", "length"))
    async def read(self, parent: ua.NodeId, handle: int, length: int) -> list[ua.Variant]:
        f = self._get(parent, handle)
        n = max(0, min(length, MAX_READ))
        chunk = f.data[f.pos:f.pos + n]
        f.pos += len(chunk)
        return [ua.Variant(chunk, ua.VariantType.ByteString)]

    @method("GetPosition", HANDLE)
    async def get_position(self, parent: ua.NodeId, handle: int) -> list[ua.Variant]:
        return [ua.Variant(self._get(parent, handle).pos, ua.VariantType.UInt64)]

    @method("SetPosition", HANDLE, Arg("Position", "position"))
    async def set_position(self, parent: ua.NodeId, handle: int, pos: int) -> list[ua.Variant]:
        f = self._get(parent, handle)
        f.pos = min(pos, len(f.data))
        return []

    async def refuse_open(self, parent: ua.NodeId, *args: Any) -> ua.StatusCode:
        # the temporary file is opened by GenerateFileForRead; a second handle is not offered
        return ua.StatusCode(ua.StatusCodes.BadNotWritable)

    @method("Close", HANDLE)
    async def close(self, parent: ua.NodeId, handle: int) -> list[ua.Variant]:
        f = self._get(parent, handle)
        del self.open[handle]
        await self._delete(f.node)
        return []

    async def close_all(self) -> None:
        if self._sweeper is not None:
            self._sweeper.cancel()
            with contextlib.suppress(BaseException):
                await self._sweeper
        for h in list(self.open):
            f = self.open.pop(h)
            await self._delete(f.node)
