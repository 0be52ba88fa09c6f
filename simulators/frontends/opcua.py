"""Controller side of OPC UA: an asyncua server exposing one VirtualController through the rumba
address space (contracts/opcua_space.py): program transfer, start, abort, state, touch counter +
result ring, request/busy/done/verdict handshake.

Security is explicit: one policy per server (Basic256Sha256 SignAndEncrypt by default, with a
certificate generated on first start), user/password checked by a user manager, anonymous only
when ``security="none"`` is asked for (tests). asyncua's defaults (every policy, every user) are
never used.
"""

from __future__ import annotations

import asyncio
import json
import logging
from collections import deque
from pathlib import Path
from typing import Any

from asyncua import Server, ua
from asyncua.common.methods import uamethod

from contracts.opcua_space import BY_ROLE, NAMESPACE_URI, RESULT_ROLES, RING_SLOTS, STATES
from simulators import thermal
from simulators.frontends import cancel_tasks
from simulators.frontends.opcua_server import check_security, free_port, secure_server

VTYPE = {"Double": ua.VariantType.Double, "Int32": ua.VariantType.Int32,
         "String": ua.VariantType.String}
HANDSHAKE = ("request", "busy", "done", "verdict")

for _name in ("asyncua.server", "asyncua.uaprotocol", "asyncua.common"):
    logging.getLogger(_name).setLevel(logging.ERROR)  # one line per rejected client is enough


class OpcUaFrontend:
    """One asyncua server for one controller; ``await start()`` returns the endpoint URL."""

    def __init__(self, controller: Any, *, security: str = "Basic256Sha256_SignAndEncrypt",
                 cert_dir: Path | None = None, users: dict[str, str] | None = None,
                 trusted_client_certs: list[Path] | None = None,
                 application_uri: str = "urn:rumba-cnc:simulator") -> None:
        check_security(security, cert_dir, users)
        self.ctrl = controller
        self.security = security
        self.cert_dir = cert_dir
        self.users = users
        self.trusted = trusted_client_certs
        self.application_uri = application_uri
        self.endpoint = ""
        self.server_certificate: Path | None = None
        self.counter = 0
        self.ack = 0
        self._pending: deque = deque()
        self.states_seen: list[str] = []  # controller states in publication order
        self._held = False
        self._ring: dict[str, list] = {}
        self._nodes: dict[str, Any] = {}
        self._mirror: dict[str, float] = {}
        self._server: Server | None = None
        self._tasks: list[asyncio.Task] = []

    async def start(self, host: str = "127.0.0.1", port: int = 0) -> str:
        """Build the server and listen; returns the endpoint URL."""
        await self.prepare(host, port)
        return await self.listen()

    async def prepare(self, host: str = "127.0.0.1", port: int = 0) -> None:
        """Everything but listening (the slow part: asyncua loads its standard nodes)."""
        if port == 0:
            port = free_port(host)
        endpoint = f"opc.tcp://{host}:{port}/rumba/"
        server, self.server_certificate = await secure_server(
            security=self.security, cert_dir=self.cert_dir, users=self.users,
            trusted=self.trusted, application_uri=self.application_uri,
            name="rumba-cnc simulated controller", endpoint=endpoint)
        ns = await server.register_namespace(NAMESPACE_URI)
        await self._build(server, ns)
        self._server = server
        self.endpoint = endpoint

    async def listen(self) -> str:
        assert self._server is not None, "prepare() first"
        await self._server.start()
        self._tasks = [asyncio.create_task(self._events()), asyncio.create_task(self._sync())]
        return self.endpoint

    async def stop(self) -> None:
        await cancel_tasks(self._tasks)
        if self._server is not None:
            await self._server.stop()
            self._server = None

    # ------------------------------------------------------------------ address space

    async def _build(self, server: Server, ns: int) -> None:
        objects = server.nodes.objects
        folders: dict[str, Any] = {}

        async def folder(path: str) -> Any:
            if path in folders:
                return folders[path]
            parent_path, _, name = path.rpartition("/")
            parent = objects if not parent_path else await folder(parent_path)
            folders[path] = await parent.add_folder(ua.NodeId(path, ns), ua.QualifiedName(name, ns))
            return folders[path]

        for spec in BY_ROLE.values():
            if spec.kind == "Method":
                continue
            parent = await folder(spec.path.rpartition("/")[0])
            name = spec.path.rpartition("/")[2]
            base = spec.kind.rstrip("[]")
            if spec.kind.endswith("[]"):
                zero = 0.0 if base == "Double" else 0
                self._ring[spec.role] = [zero] * RING_SLOTS
                value = ua.Variant(list(self._ring[spec.role]), VTYPE[base])
            else:
                value = ua.Variant("idle" if spec.role == "state" else
                                   "" if base == "String" else 0.0, VTYPE[base])
            node = await parent.add_variable(ua.NodeId(spec.path, ns), ua.QualifiedName(name, ns),
                                             value)
            if spec.kind.endswith("[]"):
                await node.write_value_rank(1)
                await node.write_array_dimensions([RING_SLOTS])
            if spec.writer == "daemon" or spec.role == "request":
                await node.set_writable()  # request: lets a test client play the part program
            self._nodes[spec.role] = node
        methods = await objects.add_object(ua.NodeId(BY_ROLE["methods"].path, ns),
                                           ua.QualifiedName("Methods", ns))
        string_arg = ua.Argument(Name="text", DataType=ua.NodeId(ua.ObjectIds.String),
                                 ValueRank=-1)
        dialect_arg = ua.Argument(Name="dialect", DataType=ua.NodeId(ua.ObjectIds.String),
                                  ValueRank=-1)
        files_arg = ua.Argument(Name="files", DataType=ua.NodeId(ua.ObjectIds.String),
                                ValueRank=-1)
        await methods.add_method(ua.NodeId(BY_ROLE["load_program"].path, ns),
                                 ua.QualifiedName("LoadProgram", ns), uamethod(self._load),
                                 [string_arg, dialect_arg, files_arg], [])
        await methods.add_method(ua.NodeId(BY_ROLE["start"].path, ns),
                                 ua.QualifiedName("Start", ns), uamethod(self._start), [], [])
        await methods.add_method(ua.NodeId(BY_ROLE["abort"].path, ns),
                                 ua.QualifiedName("Abort", ns), uamethod(self._abort), [], [])
        self._mirror = {r: 0.0 for r in HANDSHAKE}
        self._sensors = {}
        for axis in thermal.AXES:  # structure temperatures, read-only
            path = thermal.OPCUA_PATH.format(axis=axis)
            parent = await folder(path.rpartition("/")[0])
            self._sensors[axis] = await parent.add_variable(
                ua.NodeId(path, ns), ua.QualifiedName(axis, ns),
                ua.Variant(20.0, ua.VariantType.Double))

    def _sensor(self, axis: str) -> Any:
        """The Double node of an axis' structure sensor (thermal.OPCUA_PATH), made at start."""
        return self._sensors[axis]

    async def _write(self, role: str, value: Any) -> None:
        base = BY_ROLE[role].kind.rstrip("[]")
        await self._nodes[role].write_value(ua.DataValue(ua.Variant(value, VTYPE[base])))

    # ------------------------------------------------------------------ methods

    async def _load(self, parent: Any, text: str, dialect: str, files: str = "") -> None:
        if self.ctrl.state in ("running", "hold"):
            raise ua.UaStatusCodeError(ua.StatusCodes.BadInvalidState)
        try:
            aux = json.loads(files) if files else {}
            if not isinstance(aux, dict) or not all(
                    isinstance(k, str) and isinstance(v, str) for k, v in aux.items()):
                raise ValueError("files must be a JSON object of name: text")
            if aux:
                self.ctrl.files.update(aux)
            await self.ctrl.load_program(text, dialect)
        except Exception as e:
            logging.getLogger(__name__).warning("LoadProgram refused: %s", e)
            raise ua.UaStatusCodeError(ua.StatusCodes.BadInvalidArgument) from None
        self.counter = self.ack = 0
        self._pending.clear()
        self._held = False
        await self._write("touch_ack", 0.0)
        for role in RESULT_ROLES:
            self._ring[role] = [0.0 if isinstance(v, float) else 0 for v in self._ring[role]]
            await self._write(role, list(self._ring[role]))
        await self._write("touch_counter", 0.0)
        await self._write("state", "idle")
        await self._write("alarm", "")

    async def _start(self, parent: Any) -> None:
        if self.ctrl.state in ("running", "hold"):
            raise ua.UaStatusCodeError(ua.StatusCodes.BadInvalidState)
        try:
            await self.ctrl.start()
        except RuntimeError:  # no program loaded
            raise ua.UaStatusCodeError(ua.StatusCodes.BadInvalidState) from None

    async def _abort(self, parent: Any) -> None:
        await self.ctrl.abort()

    # ------------------------------------------------------------------ controller ↔ nodes

    async def _events(self) -> None:
        q = self.ctrl.subscribe()
        while True:
            ev = await q.get()
            if (type(ev).__name__ == "FaultEvent" and ev.kind == "disconnect"
                    and self._server is not None):
                for transport in list(self._server.iserver.asyncio_transports):
                    transport.close()  # connections drop; clients reconnect, ring intact
            if type(ev).__name__ in ("TouchResult", "StateChange"):
                self._pending.append(ev)
                await self._publish()

    async def _publish(self) -> None:
        """Publish results and state changes in order; a result waits while the ring is full
        (counter - ack = 32) and the control is held meanwhile, as the CNC program waits in
        its loop before overwriting an unread slot."""
        while self._pending:
            ev = self._pending[0]
            if type(ev).__name__ == "TouchResult":
                if self.counter - self.ack >= RING_SLOTS:
                    if self.ctrl.state == "running":
                        self.ctrl.feed_hold()
                        self._held = True
                    return
                await self._write_result(ev)
            else:
                state = ev.state if ev.state in STATES else "alarm"
                self.states_seen.append(state)
                await self._write("alarm", ev.alarm or "")
                await self._write("state", state)
            self._pending.popleft()
        if self._held:
            self._held = False
            if self.ctrl.state == "hold":
                await self.ctrl.start()  # resume

    async def _write_result(self, ev: Any) -> None:
        # Slot first, counter last: a client that sees the counter finds the data.
        self.counter += 1
        slot = (self.counter - 1) % RING_SLOTS
        v = ev.values
        row = {"result_seq": int(ev.seq), "result_x": float(v.get("X", 0.0)),
               "result_y": float(v.get("Y", 0.0)), "result_z": float(v.get("Z", 0.0)),
               "result_b": float(v.get("b", 0.0)), "result_c": float(v.get("c", 0.0)),
               "result_triggered": int(bool(getattr(ev, "triggered",
                                                    v.get("triggered", 1.0))))}
        for role, value in row.items():
            self._ring[role][slot] = value
            await self._write(role, list(self._ring[role]))
        await self._write("touch_counter", float(self.counter))

    async def _sync(self) -> None:
        """Mirror the handshake both ways: a client write wins, else the controller's value."""
        while True:
            for role in HANDSHAKE:
                node_value = float(await self._nodes[role].read_value())
                ctrl_value = float(getattr(self.ctrl, role))
                if node_value != self._mirror[role]:
                    setattr(self.ctrl, role, int(node_value) if role == "verdict"
                            else node_value >= 0.5)
                    self._mirror[role] = node_value
                elif ctrl_value != self._mirror[role]:
                    await self._write(role, ctrl_value)
                    self._mirror[role] = ctrl_value
            ack = int(await self._nodes["touch_ack"].read_value())
            if ack != self.ack:
                self.ack = min(ack, self.counter)
                await self._publish()
            t = float(getattr(self.ctrl, "machine_time_s", 0.0))
            if t != self._mirror.get("machine_time"):
                await self._write("machine_time", t)
                self._mirror["machine_time"] = t
            for axis, value in self.ctrl.sensor_temperatures().items():
                if self._mirror.get(f"temp_{axis}") != value:
                    await self._sensor(axis).write_value(
                        ua.DataValue(ua.Variant(value, ua.VariantType.Double)))
                    self._mirror[f"temp_{axis}"] = value
            await asyncio.sleep(0.02)
