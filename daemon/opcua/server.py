"""The daemon's OPC UA server (off unless ``opcua_server`` is configured): per machine
under Machinery's ``Machines`` folder, its OPC 40001-1 identification, MachineryItemState, the
check's live state, the last map of the linear axes (daemon/opcua/map_nodes.py), and an
OPC 40001-101 ``ResultManagement`` serving the journal's runs.

Security as the simulator's controller server (contracts/opcua_security.py): Basic256Sha256
SignAndEncrypt only, user name + password, client certificates checked against the configured
trust list; an unsecured channel gets discovery and nothing else. The official nodesets are
loaded from XML (daemon/opcua/nodesets.py), so every type NodeId and BrowseName is the spec's."""

from __future__ import annotations

import asyncio
import contextlib
import datetime as dt
import logging
import socket
from typing import Any

from asyncua import Server, ua
from asyncua.common.instantiate_util import instantiate
from asyncua.crypto.truststore import TrustStore
from asyncua.crypto.validator import CertificateValidator, CertificateValidatorOptions

from contracts.opcua_certs import ensure_certificate
from contracts.opcua_security import SecureServer
from daemon.opcua import map_nodes, nodesets, results
from daemon.opcua.auth import LimitedPasswordUsers
from daemon.opcua.config import IdentificationFile, OpcUaServerConfig
from daemon.opcua.filetransfer import ResultTransfer
from daemon.opcua.methods import Arg, method
from daemon.opcua.source import JournalSource, ResultSource
from daemon.store.journal import Store

log = logging.getLogger("rumba.opcua")
RUMBA_URI = "urn:rumba-cnc:results"  # rumba's own nodes (machine objects, the check's state)
APPLICATION_URI = "urn:rumba-cnc:daemon"
# Machinery (OPC 40001-1) and Machinery Result (OPC 40001-101) type NodeIds, in their namespaces
MACHINES_FOLDER, MACHINE_IDENTIFICATION, ITEM_STATE_MACHINE = 1001, 1012, 1002
ITEM_STATES = {"NotAvailable": 5005, "Executing": 5006, "NotExecuting": 5007}
RESULT_MANAGEMENT, RESULT_READY_EVENT = 1004, 1002
IDLE_STATES = ("IDLE", "ABORTED", "INTERRUPTED", "FAILED")
NO_TIME = dt.datetime(1601, 1, 1, tzinfo=dt.UTC)  # OPC 10000-6 §5.2.2.5: encodes as 0, "no time"
TIMEOUT = Arg("Timeout", "number")  # ms; the answers here never wait for a result


class OpcUaServerError(Exception):
    """The server cannot start; one line naming the cause."""


def _free(host: str) -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


class MachineNodes:
    """One machine's nodes and its status queue (listener → writer task, order kept)."""

    def __init__(self, name: str, uri: str) -> None:
        self.name, self.uri = name, uri
        self.vars: dict[str, Any] = {}
        self.item_state: Any = None
        self.item_state_id: Any = None
        self.management: Any = None
        self.events: list[Any] = []
        self.transfer: ResultTransfer | None = None
        self.queue: asyncio.Queue = asyncio.Queue()
        self.busy_run: str | None = None
        self.map = map_nodes.MapNodes(name)  # the last map of the linear axes


class ResultServer:
    def __init__(self, cfg: OpcUaServerConfig, store: Store | ResultSource,
                 machines: list[str]) -> None:
        """``store``: the daemon's journal, or any ResultSource (the fleet store)."""
        self.cfg, self.names = cfg, machines
        self.source: ResultSource = JournalSource(store) if isinstance(store, Store) else store
        self.server: Server | None = None
        self.machines: dict[str, MachineNodes] = {}
        self.by_management: dict[ua.NodeId, MachineNodes] = {}
        self.ns: dict[str, int] = {}
        self.idx = 0
        self.endpoint = ""
        self._tasks: list[asyncio.Task] = []

    # ------------------------------------------------------------------------------ startup
    async def start(self) -> str:
        cfg = self.cfg
        port = cfg.port or _free(cfg.host)
        server = SecureServer(user_manager=LimitedPasswordUsers(cfg.users))
        await server.init()
        self.endpoint = f"opc.tcp://{cfg.host}:{port}/rumba/results/"
        server.set_endpoint(self.endpoint)
        server.set_server_name("rumba-cnc results")
        await server.set_application_uri(APPLICATION_URI)
        server.set_security_policy([ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt])
        server.set_identity_tokens([ua.UserNameIdentityToken])
        cert, key = cfg.cert_dir / "server_cert.der", cfg.cert_dir / "server_key.pem"
        await ensure_certificate(cert, key, APPLICATION_URI, server=True)
        await server.load_certificate(str(cert))
        await server.load_private_key(str(key))
        trust = TrustStore([cfg.trusted_dir], [])
        await trust.load()
        server.set_certificate_validator(CertificateValidator(
            CertificateValidatorOptions.TRUSTED_VALIDATION
            | CertificateValidatorOptions.PEER_CLIENT, trust))
        self.ns = await nodesets.load(server, cfg.nodesets)
        self.idx = await server.register_namespace(RUMBA_URI)
        self.server = server
        for name in self.names:
            await self._machine(name, cfg.identification.get(name))
        try:
            await server.start()
        except OSError as e:
            raise OpcUaServerError(f"opcua_server: cannot listen on {cfg.host}:{port}: "
                                   f"{e.strerror or e}") from None
        for m in self.machines.values():
            self._tasks.append(asyncio.create_task(self._writer(m), name=f"opcua-{m.name}"))
        self._tasks.append(asyncio.create_task(map_nodes.follow(
            self.source, [m.map for m in self.machines.values()]), name="opcua-maps"))
        return self.endpoint

    def follow(self, interval_s: float) -> None:
        """Fleet mode (no session reports to this server): poll the source and raise the
        ResultReadyEvent of each machine's newly finished run, update its last result."""
        self._tasks.append(asyncio.create_task(self._follow(interval_s), name="opcua-follow"))

    async def _follow(self, interval_s: float) -> None:
        async def latest(name: str) -> str | None:
            return next((r.id for r in await self.source.runs(name, 50) if r.final), None)

        seen = {name: await latest(name) for name in self.machines}
        while True:
            await asyncio.sleep(interval_s)
            for name, m in self.machines.items():
                try:
                    rid = await latest(name)
                    if rid is not None and rid != seen[name] and \
                            not await self._report_pending(rid):
                        seen[name] = rid
                        await self._last_result(m, ready=rid)
                except asyncio.CancelledError:
                    raise
                except Exception as e:  # the store restarting: try again next round
                    log.warning("%s: OPC UA results: reading the store failed: %s", name, e)

    async def _report_pending(self, run_id: str) -> bool:
        """A daemon writes the report after the run's end (the store gets the run
        first): a run is announced once its report job has ended — written (its PDF is
        there) or failed (at once, with the reason) — never after a fixed wait. A job a
        daemon's crash left 'writing' is failed by that daemon's next start
        (``report_jobs.mark_abandoned``); a run without a job (an import, an older daemon)
        has no report to wait for."""
        job = await self.source.report_job(run_id)
        return job is not None and job[0] == "writing"

    async def stop(self) -> None:
        for t in self._tasks:
            t.cancel()
        for t in self._tasks:
            with contextlib.suppress(BaseException):
                await t
        if self.server is not None:
            for m in self.machines.values():
                if m.transfer is not None:
                    with contextlib.suppress(Exception):
                        await m.transfer.close_all()
            await self.server.stop()
            self.server = None

    # ------------------------------------------------------------------------ address space
    async def _machine(self, name: str, ident: IdentificationFile | None) -> None:
        assert self.server is not None
        server, idx = self.server, self.idx
        di, mach, res = (self.ns[nodesets.DI_URI], self.ns[nodesets.MACHINERY_URI],
                         self.ns[nodesets.RESULT_URI])
        uri = (ident.product_instance_uri if ident and ident.product_instance_uri else
               f"urn:rumba-cnc:machine:{name}")
        m = MachineNodes(name, uri)
        folder = server.get_node(ua.NodeId(MACHINES_FOLDER, mach))
        obj = await folder.add_object(ua.NodeId(name, idx), ua.QualifiedName(name, idx))
        # OPC 40001-1 §8: the machine's Identification (MachineIdentificationType) …
        idn = (await instantiate(obj, server.get_node(ua.NodeId(MACHINE_IDENTIFICATION, mach)),
                                   nodeid=ua.NodeId(f"{name}.Identification", idx),
                                   bname=ua.QualifiedName("Identification", di), idx=idx,
                                   instantiate_optional=False))[0]
        await self._identification(idn, name, uri, ident, di, mach)
        # … and MachineryBuildingBlocks holding its add-ins: the item state, result management
        bb = await obj.add_folder(ua.NodeId(f"{name}.MachineryBuildingBlocks", idx),
                                  ua.QualifiedName("MachineryBuildingBlocks", mach))
        await bb.add_reference(idn.nodeid, ua.ObjectIds.HasAddIn)
        st = (await instantiate(bb, server.get_node(ua.NodeId(ITEM_STATE_MACHINE, mach)),
                                  nodeid=ua.NodeId(f"{name}.MachineryItemState", idx),
                                  bname=ua.QualifiedName("MachineryItemState", mach), idx=idx,
                                  instantiate_optional=False))[0]
        m.item_state = await st.get_child(["0:CurrentState"])
        m.item_state_id = await m.item_state.get_child(["0:Id"])
        await self._item_state(m, "NotAvailable")  # until its session reports
        rm = (await instantiate(bb, server.get_node(ua.NodeId(RESULT_MANAGEMENT, res)),
                                  nodeid=ua.NodeId(f"{name}.ResultManagement", idx),
                                  bname=ua.QualifiedName("ResultManagement", res), idx=idx,
                                  instantiate_optional=True))[0]
        m.management = rm
        self.by_management[rm.nodeid] = m
        for opname, fn in (("GetLatestResult", self._latest), ("GetResultById", self._by_id),
                           ("GetResultIdListFiltered", self._filtered),
                           ("ReleaseResultHandle", self._release),
                           ("AcknowledgeResults", self._acknowledge)):
            server.link_method(await rm.get_child([f"{res}:{opname}"]), fn)
        m.transfer = ResultTransfer(server, self.source, await rm.get_child(
            [f"{res}:ResultTransfer"]), idx)
        await m.transfer.bind()
        await rm.write_attribute(ua.AttributeIds.EventNotifier, ua.DataValue(ua.Variant(
            1, ua.VariantType.Byte)))
        # asyncua delivers an event to the monitored items of its emitting node only: one
        # generator on ResultManagement (its subscribers), one on Server (a shop-wide client)
        m.events = []
        for emitter in (rm.nodeid, ua.NodeId(ua.ObjectIds.Server)):
            gen = await server.get_event_generator(ua.NodeId(RESULT_READY_EVENT, res), emitter)
            gen.event.SourceNode, gen.event.SourceName = rm.nodeid, name
            m.events.append(gen)
        # rumba's check state (its own namespace): what the HMI shows
        check = await obj.add_object(ua.NodeId(f"{name}.Check", idx),
                                     ua.QualifiedName("Check", idx))
        for var, value, vt in (("State", "IDLE", ua.VariantType.String),
                               ("RunId", "", ua.VariantType.String),
                               ("DoneTouches", 0, ua.VariantType.UInt32),
                               ("TotalTouches", 0, ua.VariantType.UInt32),
                               ("Progress_percent", 0.0, ua.VariantType.Double),
                               ("LastResultId", "", ua.VariantType.String),
                               ("LastVerdict", "", ua.VariantType.String),
                               ("LastVerdictTime", NO_TIME, ua.VariantType.DateTime),
                               ("LastResultEvaluation", 0, ua.VariantType.Int32)):
            m.vars[var] = await check.add_variable(ua.NodeId(f"{name}.Check.{var}", idx),
                                                   ua.QualifiedName(var, idx),
                                                   ua.Variant(value, vt))
        await m.map.add(obj, idx)
        self.machines[name] = m
        await self._last_result(m)

    async def _identification(self, node: Any, name: str, uri: str,
                              ident: IdentificationFile | None, di: int, mach: int) -> None:
        async def put(ns: int, key: str, value: Any, vt: ua.VariantType) -> None:
            try:
                child = await node.get_child([f"{ns}:{key}"])
                await child.write_value(ua.Variant(value, vt))
            except ua.UaStatusCodeError:  # an optional property: added with its official name
                await node.add_property(ua.NodeId(f"{name}.Identification.{key}", self.idx),
                                        ua.QualifiedName(key, ns), ua.Variant(value, vt))

        lt = ua.VariantType.LocalizedText
        await put(di, "Manufacturer", ua.LocalizedText(ident.manufacturer if ident else ""), lt)
        await put(di, "SerialNumber", ident.serial_number if ident else "",
                  ua.VariantType.String)
        await put(di, "ProductInstanceUri", uri, ua.VariantType.String)
        await put(di, "ComponentName", ua.LocalizedText(name), lt)
        if ident and ident.model:
            await put(di, "Model", ua.LocalizedText(ident.model), lt)
        if ident and ident.year_of_construction:
            await put(mach, "YearOfConstruction", ident.year_of_construction,
                      ua.VariantType.UInt16)
        if ident and ident.location:
            await put(mach, "Location", ident.location, ua.VariantType.String)

    # ------------------------------------------------------------------------------ methods
    def _of(self, parent: ua.NodeId) -> MachineNodes:
        m = self.by_management.get(parent)
        if m is None:
            raise ua.UaStatusCodeError(ua.StatusCodes.BadNodeIdUnknown)
        return m

    async def _answer(self, m: MachineNodes, run: Any, error: int = 0) -> list[ua.Variant]:
        if run is None:
            data = ua.ResultDataType(ResultMetaData=ua.ResultMetaDataType(ResultId=""))
        else:
            data = await results.result(self.source, run, m.uri, self.idx)
        return [ua.Variant(0, ua.VariantType.UInt32),  # no handles: results stay available
                ua.Variant(data, ua.VariantType.ExtensionObject),
                ua.Variant(error, ua.VariantType.Int32)]

    @method("GetLatestResult", TIMEOUT)
    async def _latest(self, parent: ua.NodeId, timeout: float) -> list[ua.Variant]:
        m = self._of(parent)
        run = next((r for r in await self.source.runs(m.name, 50) if r.final), None)
        return await self._answer(m, run, 0 if run else results.ERR_NO_RESULT)

    @method("GetResultById", Arg("ResultId", "string"), TIMEOUT)
    async def _by_id(self, parent: ua.NodeId, rid: str, timeout: float) -> list[ua.Variant]:
        m = self._of(parent)
        run = await self.source.run(rid)
        if run is None or run.machine != m.name:
            return await self._answer(m, None, results.ERR_UNKNOWN_ID)
        return await self._answer(m, run)

    @method("GetResultIdListFiltered", Arg("Filter", "filter"), Arg("OrderedBy", "any"),
            Arg("MaxResults", "count"), TIMEOUT)
    async def _filtered(self, parent: ua.NodeId, flt: Any, ordered: Any, max_results: int,
                        timeout: float) -> list[ua.Variant]:
        m = self._of(parent)
        try:
            ids = await results.filtered_ids(self.source, m.name,
                                             flt if flt is not None else ua.ContentFilter(),
                                             max_results)
            err = 0
        except results.FilterError as e:
            log.info("%s: GetResultIdListFiltered: %s", m.name, e)
            ids, err = [], results.ERR_FILTER
        return [ua.Variant(0, ua.VariantType.UInt32), ua.Variant(ids, ua.VariantType.String),
                ua.Variant(err, ua.VariantType.Int32)]

    @method("ReleaseResultHandle", Arg("ResultHandle", "count"))
    async def _release(self, parent: ua.NodeId, handle: int) -> list[ua.Variant]:
        self._of(parent)
        return [ua.Variant(0, ua.VariantType.Int32)]

    @method("AcknowledgeResults", Arg("ResultIds", "strings"))
    async def _acknowledge(self, parent: ua.NodeId, ids: list[str]) -> list[ua.Variant]:
        self._of(parent)  # results stay in the journal whatever a client acknowledges
        return [ua.Variant([0] * len(ids), ua.VariantType.Int32),
                ua.Variant(0, ua.VariantType.Int32)]

    # ------------------------------------------------------------------------- live state
    def listener(self, machine: str) -> Any:
        """The session's status listener for ``machine`` (never blocks: queued)."""
        m = self.machines[machine]
        return m.queue.put_nowait

    async def _writer(self, m: MachineNodes) -> None:
        while True:
            st = await m.queue.get()
            try:
                await self._status(m, st)
            except asyncio.CancelledError:
                raise
            except Exception:  # a client-facing mirror must never break the daemon
                log.exception("%s: OPC UA state update failed", m.name)

    async def _status(self, m: MachineNodes, st: dict[str, Any]) -> None:
        state, done, total = st["state"], int(st["done"] or 0), int(st["total"] or 0)
        item = ("NotAvailable" if not st["link_ok"] else
                "NotExecuting" if state in IDLE_STATES else "Executing")
        await self._item_state(m, item)
        await m.vars["State"].write_value(ua.Variant(state, ua.VariantType.String))
        await m.vars["RunId"].write_value(ua.Variant(st["run_id"] or "", ua.VariantType.String))
        await m.vars["DoneTouches"].write_value(ua.Variant(done, ua.VariantType.UInt32))
        await m.vars["TotalTouches"].write_value(ua.Variant(total, ua.VariantType.UInt32))
        await m.vars["Progress_percent"].write_value(ua.Variant(
            100.0 * done / total if total else 0.0, ua.VariantType.Double))
        if state not in IDLE_STATES:
            m.busy_run = st["run_id"]
        elif m.busy_run is not None:  # a run ended: its result is in the journal now
            if ((st.get("verdict") or {}).get("report_state") == "writing"
                    and st["run_id"] == m.busy_run):
                return  # "result ready" once its PDF is there (or failed)
            run_id, m.busy_run = m.busy_run, None
            await self._last_result(m, ready=run_id)

    async def _item_state(self, m: MachineNodes, item: str) -> None:
        await m.item_state.write_value(ua.LocalizedText(item, "en"))
        await m.item_state_id.write_value(ua.Variant(ua.NodeId(
            ITEM_STATES[item], self.ns[nodesets.MACHINERY_URI]), ua.VariantType.NodeId))

    async def _last_result(self, m: MachineNodes, ready: str | None = None) -> None:
        await map_nodes.refresh(self.source, m.map)
        run = next((r for r in await self.source.runs(m.name, 50) if r.final), None)
        if run is not None:
            v = await self.source.verdict(run.id)
            ev = results.evaluation(run.verdict, v["checks"] if v else None)
            when = dt.datetime.fromtimestamp(run.ended_at or run.started_at, dt.UTC)
            await m.vars["LastResultId"].write_value(ua.Variant(run.id, ua.VariantType.String))
            await m.vars["LastVerdict"].write_value(ua.Variant(run.verdict or run.state,
                                                               ua.VariantType.String))
            await m.vars["LastVerdictTime"].write_value(ua.Variant(when, ua.VariantType.DateTime))
            await m.vars["LastResultEvaluation"].write_value(ua.Variant(ev, ua.VariantType.Int32))
        if ready is None:
            return
        done = await self.source.run(ready)
        if done is None:
            return
        data = await results.result(self.source, done, m.uri, self.idx)
        job = await self.source.report_job(ready)
        why = f"; report not written: {job[1]}" if job and job[0] == "failed" else ""
        for gen in m.events:
            gen.event.Result = data
            gen.event.Message = ua.LocalizedText(f"{m.name}: result {ready} ready "
                                                 f"({done.verdict or done.state}){why}", "en")
            gen.event.Severity = 500
            await gen.trigger()
