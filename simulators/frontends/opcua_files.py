"""The OPC UA file system a controller's server offers (OPC UA Part 5 Annex C / Part 20): a folder
of FileDirectoryType with CreateFile / Delete, files of FileType with Open / Read / Write / Close /
GetPosition / SetPosition and their Size, Writable, UserWritable, OpenCount, on an asyncua server.

Status codes as Part 20 gives them: a name that exists → BadBrowseNameDuplicated; an unknown
handle → BadInvalidArgument; a write on a handle opened for reading, or an open for writing of a
file already open (or locked by its owner: a selected, running program) → BadNotWritable /
BadInvalidState; a bad mode → BadInvalidArgument. CreateDirectory and MoveOrCopy answer
BadNotImplemented here (the simulated control does not need them; a real one offers them).
"""

from __future__ import annotations

import inspect
import itertools
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from asyncua import Server, ua
from asyncua.common.methods import uamethod

MAX_FILE_BYTES = 4 * 1024 * 1024  # a part program larger than this is refused (BadOutOfRange)
_handles = itertools.count(1)


class Refused(Exception):
    """A method call the control refuses: answered with ``code`` as the call's status (an
    exception escaping an asyncua method would become BadUnexpectedError)."""

    def __init__(self, code: int) -> None:
        super().__init__(ua.StatusCodes.__dict__.get(code, code))
        self.code = code


def _bad(code: int) -> Refused:
    return Refused(code)


def method(fn: Callable[..., Any], *bound: Any) -> Any:
    """``fn(*bound, *args)`` as an asyncua method callback run on the server's event loop (a
    plain callback would run in a worker thread), ``Refused`` answered as the call's status."""
    async def call(parent: Any, *args: Any) -> Any:
        try:
            out = fn(*bound, *args)
            return await out if inspect.isawaitable(out) else out
        except Refused as e:
            return ua.StatusCode(e.code)
    return uamethod(call)


@dataclass
class SimFile:
    """One file: its bytes and its open handles (handle → [mode, position])."""

    name: str
    node: Any
    data: bytearray = field(default_factory=bytearray)
    handles: dict[int, list[int]] = field(default_factory=dict)

    def writer(self) -> bool:
        return any(m & 2 for m, _ in self.handles.values())


class SimFolder:
    """One FileDirectoryType folder of files, on ``server`` under ``parent``; ``name_ok`` says
    which file names the control accepts (others → BadInvalidArgument); ``on_close`` is told
    every file closed after a write (the control's own view of its program memory);
    ``busy`` why the control refuses to write or delete a file now ("" = it does not: a
    program running in a channel is locked, a selected one in reset is not)."""

    def __init__(self, server: Server, ns: int, path: str, name: str,
                 name_ok: Callable[[str], bool] = lambda n: bool(re.fullmatch(r"[^/\\]{1,64}", n)),
                 on_close: Callable[[SimFile], None] | None = None,
                 busy: Callable[[SimFile], str] = lambda f: "") -> None:
        self.server = server
        self.ns = ns
        self.path = path
        self.name = name
        self.name_ok = name_ok
        self.on_close = on_close
        self.busy = busy
        self.files: dict[str, SimFile] = {}
        self.node: Any = None

    async def build(self, parent: Any) -> Any:
        self.node = await parent.add_object(ua.NodeId(self.path, self.ns),
                                            ua.QualifiedName(self.name, self.ns),
                                            objecttype=ua.ObjectIds.FileDirectoryType)
        for child in await self.node.get_children():
            name = (await child.read_browse_name()).Name
            if name.startswith("<"):  # asyncua instantiates the placeholders: not real nodes
                await self.server.delete_nodes([child])
            elif name == "CreateFile":
                self.server.link_method(child, method(self._create_file))
            elif name == "Delete":
                self.server.link_method(child, method(self._delete))
            elif name in ("CreateDirectory", "MoveOrCopy"):
                self.server.link_method(child, method(self._not_here))
        return self.node

    def file(self, name: str) -> SimFile | None:
        return self.files.get(name.upper())

    async def put(self, name: str, data: bytes) -> SimFile:
        """A file stored by the control itself (e.g. one the operator loaded)."""
        f = self.file(name) or await self._add(name)
        f.data = bytearray(data)
        await self._size(f)
        return f

    # ------------------------------------------------------------------ folder methods
    def _not_here(self, *args: Any) -> None:
        raise _bad(ua.StatusCodes.BadNotImplemented)

    async def _create_file(self, file_name: Any, request_open: Any) -> tuple:
        if not isinstance(file_name, str) or not isinstance(request_open, bool):
            raise _bad(ua.StatusCodes.BadTypeMismatch)
        if not self.name_ok(file_name):
            raise _bad(ua.StatusCodes.BadInvalidArgument)
        if self.file(file_name) is not None:
            raise _bad(ua.StatusCodes.BadBrowseNameDuplicated)
        f = await self._add(file_name)
        handle = 0
        if request_open:  # Part 20: opened with the Read and Write bits set
            handle = next(_handles)
            f.handles[handle] = [3, 0]
            await self._open_count(f)
        return (ua.Variant(f.node.nodeid, ua.VariantType.NodeId),
                ua.Variant(handle, ua.VariantType.UInt32))

    async def _delete(self, target: Any) -> None:
        if not isinstance(target, ua.NodeId):
            raise _bad(ua.StatusCodes.BadTypeMismatch)
        f = next((f for f in self.files.values() if f.node.nodeid == target), None)
        if f is None:
            raise _bad(ua.StatusCodes.BadNotFound)
        if self.busy(f) or f.handles:
            raise _bad(ua.StatusCodes.BadInvalidState)
        del self.files[f.name.upper()]
        await self.server.delete_nodes([f.node], recursive=True)

    async def _add(self, name: str) -> SimFile:
        node = await self.node.add_object(ua.NodeId(f"{self.path}/{name}", self.ns),
                                          ua.QualifiedName(name, self.ns),
                                          objecttype=ua.ObjectIds.FileType)
        f = SimFile(name, node)
        self.files[name.upper()] = f
        bind = {"Open": self._open, "Close": self._close, "Read": self._read,
                "Write": self._write, "GetPosition": self._get_pos,
                "SetPosition": self._set_pos}
        for child in await node.get_children():
            bname = (await child.read_browse_name()).Name
            if bname in bind:
                self.server.link_method(child, method(bind[bname], f))
            elif bname in ("Writable", "UserWritable"):
                await child.write_value(ua.Variant(True, ua.VariantType.Boolean))
        await self._size(f)
        await self._open_count(f)
        return f

    # ------------------------------------------------------------------ file methods
    def _handle(self, f: SimFile, handle: Any) -> list[int]:
        if not isinstance(handle, int) or isinstance(handle, bool):
            raise _bad(ua.StatusCodes.BadTypeMismatch)
        if handle not in f.handles:
            raise _bad(ua.StatusCodes.BadInvalidArgument)
        return f.handles[handle]

    async def _open(self, f: SimFile, mode: Any) -> ua.Variant:
        if not isinstance(mode, int) or isinstance(mode, bool):
            raise _bad(ua.StatusCodes.BadTypeMismatch)
        if mode <= 0 or mode > 15 or (mode & 12 and not mode & 2):
            raise _bad(ua.StatusCodes.BadInvalidArgument)  # erase/append need write
        if mode & 2:
            if self.busy(f):
                raise _bad(ua.StatusCodes.BadNotWritable)
            if f.handles:  # Part 20: a file open for writing is open exactly once
                raise _bad(ua.StatusCodes.BadInvalidState)
            if mode & 4:
                f.data = bytearray()
        elif f.writer():
            raise _bad(ua.StatusCodes.BadInvalidState)
        handle = next(_handles)
        f.handles[handle] = [mode, len(f.data) if mode & 8 else 0]
        await self._open_count(f)
        return ua.Variant(handle, ua.VariantType.UInt32)

    async def _close(self, f: SimFile, handle: Any) -> None:
        mode, _ = self._handle(f, handle)
        del f.handles[handle]
        await self._open_count(f)
        await self._size(f)
        if mode & 2 and self.on_close is not None:
            self.on_close(f)

    def _read(self, f: SimFile, handle: Any, length: Any) -> ua.Variant:
        h = self._handle(f, handle)
        if not h[0] & 1:
            raise _bad(ua.StatusCodes.BadInvalidState)
        if not isinstance(length, int) or length < 0:
            raise _bad(ua.StatusCodes.BadInvalidArgument)
        chunk = bytes(f.data[h[1]:h[1] + length])
        h[1] += len(chunk)
        return ua.Variant(chunk, ua.VariantType.ByteString)

    def _write(self, f: SimFile, handle: Any, data: Any) -> None:
        h = self._handle(f, handle)
        if not h[0] & 2:
            raise _bad(ua.StatusCodes.BadInvalidState)
        if data is None:
            return
        if not isinstance(data, bytes | bytearray):
            raise _bad(ua.StatusCodes.BadTypeMismatch)
        if h[1] + len(data) > MAX_FILE_BYTES:
            raise _bad(ua.StatusCodes.BadOutOfRange)
        f.data[h[1]:h[1] + len(data)] = data
        h[1] += len(data)

    def _get_pos(self, f: SimFile, handle: Any) -> ua.Variant:
        return ua.Variant(self._handle(f, handle)[1], ua.VariantType.UInt64)

    def _set_pos(self, f: SimFile, handle: Any, position: Any) -> None:
        h = self._handle(f, handle)
        if not isinstance(position, int) or position < 0:
            raise _bad(ua.StatusCodes.BadInvalidArgument)
        h[1] = min(position, len(f.data))

    async def _size(self, f: SimFile) -> None:
        node = await f.node.get_child("Size")
        await node.write_value(ua.Variant(len(f.data), ua.VariantType.UInt64))

    async def _open_count(self, f: SimFile) -> None:
        node = await f.node.get_child("OpenCount")
        await node.write_value(ua.Variant(len(f.handles), ua.VariantType.UInt16))
