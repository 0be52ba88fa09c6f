"""Controller side of the SINUMERIK OPC UA profile: an asyncua server answering as a SINUMERIK
840D sl OPC UA server does for what rumba uses (contracts/sinumerik_space.py): "Sinumerik" with
the channel's R parameters (Doubles, ``/Channel/Parameter/R[u1,n]``, live from the controller's
variables), NC-global GUDs, the program and channel state, the file system (folders "Part
Programs", "Sub Programs", "Work Pieces" of OPC UA Part 5 FileDirectoryType) and the ``Select``
method under "Methods". There is no NC start method: a selected program runs when the machine's
PLC starts it (``plc_starts``: on ``program_ready`` = 1, as a shop's PLC does on the start
request) or the operator presses NC start (``nc_start()``, the simulator's ``start`` command).

Refusals as the control gives them: Select of a file that is not there or of another channel
(BadInvalidArgument), while a program runs (BadInvalidState); a write of an R parameter as
anything but a Double (BadTypeMismatch); the file system's refusals (simulators/frontends/
opcua_files.py); every service but discovery on an unsecured channel (contracts/opcua_security).
"""

from __future__ import annotations

import asyncio
import logging
import re
from pathlib import Path
from typing import Any

from asyncua import Server, ua

from contracts.sinumerik_space import (
    FILE_SYSTEM,
    GUD_PATH,
    HANDSHAKE_ROLES,
    METHODS,
    NAMESPACE_URI,
    PROGRAM_FOLDERS,
    PROGRAM_NAME,
    R_COUNT,
    ROOT,
    SELECT,
    file_name,
    r_node,
    role_path,
    select_path,
)
from simulators import thermal
from simulators.frontends import cancel_tasks
from simulators.frontends.opcua_files import Refused, SimFile, SimFolder, method
from simulators.frontends.opcua_server import free_port, secure_server
from simulators.frontends.ring_pacing import RingPacer

log = logging.getLogger(__name__)
for _name in ("asyncua.server", "asyncua.uaprotocol", "asyncua.common"):
    logging.getLogger(_name).setLevel(logging.ERROR)

_R = re.compile(r"^/Channel/Parameter/R\[u(\d+),(\d+)\]$")
_GUD = re.compile(r"^/NC/_N_NC_GD3_ACX/([A-Z_][A-Z0-9_]{0,31})$")


def _program_file(name: str) -> bool:
    """A part-program file name the control accepts (<NAME>.MPF / .SPF)."""
    stem, _, ext = name.rpartition(".")
    return bool(PROGRAM_NAME.fullmatch(stem.upper())) and ext.upper() in ("MPF", "SPF", "WPF")


def program_state(state: str, waiting: bool) -> tuple[int, int]:
    """(progStatus, chanStatus) of the controller state: running → in progress / active; held
    by the result handshake → waiting / active; feed hold or M0 → stopped / interrupted; an
    alarm → interrupted / interrupted; idle, ended or reset → aborted / reset."""
    if state == "running":
        return 3, 2
    if state == "hold":
        return (4, 2) if waiting else (2, 1)
    if state == "alarm":
        return 1, 1
    return 5, 0


class SinumerikFrontend:
    """One SINUMERIK-like OPC UA server for one controller; ``await start()`` returns the URL."""

    def __init__(self, controller: Any, *, security: str = "Basic256Sha256_SignAndEncrypt",
                 cert_dir: Path | None = None, users: dict[str, str] | None = None,
                 trusted_client_certs: list[Path] | None = None, channel: int = 1,
                 plc_starts: bool = True, handshake: dict[str, str] | None = None,
                 guds: tuple[str, ...] = (),
                 application_uri: str = "urn:rumba-cnc:simulator:sinumerik") -> None:
        self.ctrl = controller
        self.security, self.cert_dir, self.users = security, cert_dir, users
        self.trusted = trusted_client_certs
        self.channel = channel
        self.plc_starts = plc_starts
        self.guds = tuple(g.upper() for g in guds)
        self.application_uri = application_uri
        # role → variable name in the controller (R<n> or a GUD's name)
        self.handshake = {r: self._variable(p) for r, p in {
            **{r: role_path(r, channel) for r in HANDSHAKE_ROLES}, **(handshake or {})}.items()}
        self.endpoint = ""
        self.server_certificate: Path | None = None
        self.folders: dict[str, SimFolder] = {}
        self.selected: SimFile | None = None
        self.nc_starts = 0  # NC starts given (PLC or operator), for tests
        self.pacer = RingPacer(controller, "siemens")
        self._server: Server | None = None
        self._ns = 0
        self._nodes: dict[str, ua.NodeId] = {}  # variable name → node id (R, GUD)
        self._state_nodes: dict[str, Any] = {}
        self._dirty: set[str] = set()
        self._wake = asyncio.Event()
        self._tasks: list[asyncio.Task] = []
        controller.variable_listeners.append(self._written)

    def _variable(self, path: str) -> str:
        m = _R.fullmatch(path)
        if m and int(m.group(1)) == self.channel and int(m.group(2)) < R_COUNT:
            return f"R{int(m.group(2))}"
        m = _GUD.fullmatch(path)
        if m:
            return m.group(1)
        raise ValueError(f"{path}: not an R parameter of channel {self.channel} (R0-R"
                         f"{R_COUNT - 1}) or an NC-global GUD /NC/_N_NC_GD3_ACX/<NAME>")

    async def start(self, host: str = "127.0.0.1", port: int = 0) -> str:
        port = port or free_port(host)
        endpoint = f"opc.tcp://{host}:{port}/"
        server, self.server_certificate = await secure_server(
            security=self.security, cert_dir=self.cert_dir, users=self.users,
            trusted=self.trusted, application_uri=self.application_uri,
            name="SINUMERIK OPC UA server (rumba-cnc simulator)", endpoint=endpoint)
        self._ns = await server.register_namespace(NAMESPACE_URI)
        self._server = server
        await self._build(server)
        await server.start()
        self._tasks = [asyncio.create_task(self._events()), asyncio.create_task(self._sync())]
        self.endpoint = endpoint
        return endpoint

    async def stop(self) -> None:
        await cancel_tasks(self._tasks)
        self.pacer.close()
        if self._written in self.ctrl.variable_listeners:
            self.ctrl.variable_listeners.remove(self._written)
        if self._server is not None:
            await self._server.stop()
            self._server = None

    # ------------------------------------------------------------------ address space
    async def _build(self, server: Server) -> None:
        ns = self._ns
        root = await server.nodes.objects.add_object(ua.NodeId(ROOT, ns),
                                                     ua.QualifiedName(ROOT, ns))
        params = await root.add_folder(ua.NodeId("/Channel/Parameter", ns),
                                       ua.QualifiedName("Parameter", ns))
        for n in range(R_COUNT):
            await self._variable_node(params, r_node(n, self.channel), f"R{n}")
        gud = await root.add_folder(ua.NodeId("/NC/_N_NC_GD3_ACX", ns),
                                    ua.QualifiedName("GUD", ns))
        for name in self.guds:
            await self._variable_node(gud, GUD_PATH.format(name=name), name)
        state = await root.add_folder(ua.NodeId("/Channel/State", ns),
                                      ua.QualifiedName("State", ns))
        for key in ("progStatus", "chanStatus"):
            self._state_nodes[key] = await state.add_variable(
                ua.NodeId(f"/Channel/State/{key}", ns), ua.QualifiedName(key, ns),
                ua.Variant(5 if key == "progStatus" else 0, ua.VariantType.UInt16))
        info = await root.add_folder(ua.NodeId("/Channel/ProgramInfo", ns),
                                     ua.QualifiedName("ProgramInfo", ns))
        self._state_nodes["selected"] = await info.add_variable(
            ua.NodeId("/Channel/ProgramInfo/selectedWorkPProg", ns),
            ua.QualifiedName("selectedWorkPProg", ns), ua.Variant("", ua.VariantType.String))
        fs = await root.add_object(ua.NodeId("/".join(FILE_SYSTEM), ns),
                                   ua.QualifiedName(FILE_SYSTEM[-1], ns))
        for name in PROGRAM_FOLDERS:
            folder = SimFolder(server, ns, f"{'/'.join(FILE_SYSTEM)}/{name}", name,
                               name_ok=_program_file, busy=self._busy)
            await folder.build(fs)
            self.folders[name] = folder
        methods = await root.add_object(ua.NodeId("/".join(METHODS), ns),
                                        ua.QualifiedName(METHODS[-1], ns))
        path_arg = ua.Argument(Name="Path", DataType=ua.NodeId(ua.ObjectIds.String),
                               ValueRank=-1)
        channel_arg = ua.Argument(Name="Channel", DataType=ua.NodeId(ua.ObjectIds.UInt32),
                                  ValueRank=-1)
        await methods.add_method(ua.NodeId(f"{'/'.join(METHODS)}/{SELECT}", ns),
                                 ua.QualifiedName(SELECT, ns), method(self._select),
                                 [path_arg, channel_arg], [])

    async def _variable_node(self, parent: Any, path: str, name: str) -> None:
        nodeid = ua.NodeId(path, self._ns)
        node = await parent.add_variable(nodeid, ua.QualifiedName(path.rpartition("/")[2],
                                                                  self._ns),
                                         ua.Variant(0.0, ua.VariantType.Double))
        await node.set_writable()
        assert self._server is not None
        self._server.set_attribute_value_callback(nodeid, lambda *_a, n=name: self._read(n))
        self._server.set_attribute_value_setter(nodeid,
                                                lambda nd, attr, dv, n=name: self._set(n, dv))
        # the callback cleared the stored value, and with it the server's type check of a
        # client's write (a Double node written as an Int32 is BadTypeMismatch): put it back
        self._server.iserver.aspace[nodeid].attributes[ua.AttributeIds.Value].value = \
            ua.DataValue(ua.Variant(0.0, ua.VariantType.Double))
        self._nodes[name] = nodeid

    def _read(self, name: str) -> ua.DataValue:
        v = self.ctrl.variables.get(name, 0.0)
        return ua.DataValue(ua.Variant(float(v) if isinstance(v, int | float) else 0.0,
                                       ua.VariantType.Double))

    def _set(self, name: str, dv: ua.DataValue) -> None:
        """A write to an R parameter / GUD node: the client's goes to the controller's variable
        (the notification writes of ``_publish`` carry the value it already holds)."""
        value = dv.Value.Value if dv.Value is not None else None
        if not isinstance(value, float):
            return  # a Double node: the server refused other types before this
        if self.ctrl.variables.get(name) != value:
            self.ctrl.variables[name] = value

    # ------------------------------------------------------------------ the control's side
    def _written(self, name: str, value: Any) -> None:
        """Every variable write (the program's, a client's): publish it; the PLC model."""
        if name in self._nodes:
            self._dirty.add(name)
            self._wake.set()
        role = next((r for r, v in self.handshake.items() if v == name), None)
        if role in ("busy", "done") and isinstance(value, float):
            setattr(self.ctrl, role, value >= 0.5)
        elif role == "verdict" and isinstance(value, float) and name != "R4":
            self.ctrl.verdict = round(value)  # R4 is the controller's own verdict variable
        elif role == "program_ready" and self.plc_starts and isinstance(value, float) \
                and value >= 0.5 and self.selected is not None \
                and self.ctrl.state not in ("running", "hold"):
            asyncio.get_running_loop().create_task(self.nc_start())

    async def nc_start(self) -> None:
        """NC start at the machine (the PLC's or the operator's): the selected program runs
        (or a held one goes on); nothing selected → the control refuses (logged)."""
        try:
            await self.ctrl.start()
        except RuntimeError as e:
            log.warning("NC start refused: %s", e)
            return
        self.nc_starts += 1

    def _busy(self, f: SimFile) -> str:
        """The selected program is locked while it runs in the channel (in reset it may be
        overwritten, and is selected again to take effect)."""
        if f is self.selected and self.ctrl.state in ("running", "hold", "alarm"):
            return f"selected in channel {self.channel}, {self.ctrl.state}"
        return ""

    async def _select(self, path: Any, channel: Any) -> None:
        if not isinstance(path, str) or not isinstance(channel, int):
            raise Refused(ua.StatusCodes.BadTypeMismatch)
        if channel != self.channel:
            raise Refused(ua.StatusCodes.BadInvalidArgument)
        folder = self.folders[PROGRAM_FOLDERS[0]]
        f = next((f for f in folder.files.values()
                  if select_path(f.name.rpartition(".")[0].upper()) == path), None)
        if f is None or not f.name.upper().endswith(".MPF"):
            raise Refused(ua.StatusCodes.BadInvalidArgument)
        if self.ctrl.state in ("running", "hold") or f.handles:
            raise Refused(ua.StatusCodes.BadInvalidState)
        try:
            text = f.data.decode("ascii")
        except UnicodeDecodeError:
            raise Refused(ua.StatusCodes.BadInvalidArgument) from None
        await self.ctrl.load_program(text, "siemens")
        self.selected = f
        await self._state_nodes["selected"].write_value(ua.Variant(path, ua.VariantType.String))

    async def _events(self) -> None:
        q = self.ctrl.subscribe()
        while True:
            ev = await q.get()
            kind = type(ev).__name__
            if kind == "FaultEvent" and ev.kind == "disconnect" and self._server is not None:
                for transport in list(self._server.iserver.asyncio_transports):
                    transport.close()  # connections drop; the program and its R params stay
            elif kind == "StateChange":
                await self._publish_state()

    async def _publish_state(self) -> None:
        prog, chan = program_state(self.ctrl.state, self.pacer.held)
        for key, value in (("progStatus", prog), ("chanStatus", chan)):
            node = self._state_nodes[key]
            if await node.read_value() != value:
                await node.write_value(ua.Variant(value, ua.VariantType.UInt16))

    async def _sync(self) -> None:
        """Notifications of changed variables (subscriptions fire on writes), the request flag
        the tests drop as the PLC would, the program state."""
        seen = {role: bool(getattr(self.ctrl, role)) for role in ("done", "busy")}
        while True:
            request = self.handshake["request"]
            raised = self.ctrl.variables.get(request, 0.0) >= 0.5
            if bool(self.ctrl.request) != raised:  # the PLC's flag follows the control's
                self.ctrl.variables[request] = 1.0 if self.ctrl.request else 0.0
            for role in ("done", "busy"):  # cleared on the control's side (its new request)
                now = bool(getattr(self.ctrl, role))
                if now != seen[role] and (self.ctrl.variables.get(self.handshake[role], 0.0)
                                          >= 0.5) != now:
                    self.ctrl.variables[self.handshake[role]] = 1.0 if now else 0.0
                seen[role] = now
            for axis, value in self.ctrl.sensor_temperatures().items():
                # the PLC copies the structure sensors into R91-R93 (also when no program runs)
                dict.__setitem__(self.ctrl.variables, thermal.SIEMENS_VARIABLE[axis], value)
            dirty, self._dirty = self._dirty, set()
            assert self._server is not None
            for name in sorted(dirty):
                # the value held now (the setter sees no change: nothing written back)
                await self._server.write_attribute_value(self._nodes[name], self._read(name))
            await self._publish_state()
            self._wake.clear()
            waiter = asyncio.ensure_future(self._wake.wait())
            try:  # not wait_for: on Python 3.11 it can swallow the stop's cancellation
                await asyncio.wait({waiter}, timeout=0.02)
            finally:
                waiter.cancel()

    async def operator_select(self, name: str) -> None:
        """The operator selects part program ``name`` at the machine (``Refused`` as Select)."""
        await self._select(select_path(name), self.channel)

    def diagnose(self) -> str:
        """Where the simulated control stands, for a test's failure message."""
        v = self.ctrl.variables
        ring = {n: v.get(n) for n in ("R99", "R188", "R189")}
        hs = {r: v.get(n) for r, n in self.handshake.items()}
        return (f"selected {self.selected.name if self.selected else None}, ring {ring}, "
                f"handshake {hs}, pacer held {self.pacer.held}, NC starts {self.nc_starts}")

    async def put_program(self, name: str, text: str) -> None:
        """A part program stored on the control by other means (the operator, a USB stick)."""
        await self.folders[PROGRAM_FOLDERS[0]].put(file_name(name), text.encode("ascii"))
