#!/usr/bin/env node
// Independent OPC UA client (node-opcua) for rumba's results server: checks the
// address space against the official companion nodesets, reads identification and state, calls
// the OPC 40001-101 methods, waits for a ResultReadyEvent and downloads a report.
//
//   node tests/peers/opcua_results_client.js ENDPOINT_URL --cert C.pem --key K.pem --app-uri URI
//        [--user U --password P] [--security none] [--ids ID,ID,...] [--download ID]
//        [--wait-event] [--machine NAME] [--timeout MS]
//
// Output: JSON lines on stdout. {"event":"subscribed"} once the event subscription is live (the
// test then ends a run), then one final {"ok":true,…} or {"ok":false,"error":…}. Exit 0 / 2.
"use strict";
const fs = require("fs");
const os = require("os");
const path = require("path");
const crypto = require("crypto");

const emit = (obj) => process.stdout.write(`${JSON.stringify(obj)}\n`);
for (const k of ["log", "info", "warn", "debug"]) {
  console[k] = (...a) => process.stderr.write(`${a.map(String).join(" ")}\n`);
}

function loadOpcua() {
  const roots = [process.env.RUMBA_NODE_PEERS, path.join(__dirname, "..", "..", ".peers", "node")];
  for (const root of roots.filter(Boolean)) {
    try {
      return require(require.resolve("node-opcua", { paths: [root] }));
    } catch (_) { /* next */ }
  }
  return require("node-opcua");
}

function parseArgs(argv) {
  const o = { ids: [], security: "SignAndEncrypt", timeout: 60000 };
  const pos = [];
  for (let i = 0; i < argv.length; i++) {
    const a = argv[i];
    const v = () => argv[++i];
    if (a === "--cert") o.cert = v();
    else if (a === "--key") o.key = v();
    else if (a === "--app-uri") o.appUri = v();
    else if (a === "--user") o.user = v();
    else if (a === "--password") o.password = v();
    else if (a === "--security") o.security = v();
    else if (a === "--ids") o.ids = v().split(",").filter(Boolean);
    else if (a === "--download") o.download = v();
    else if (a === "--wait-event") o.waitEvent = true;
    else if (a === "--machine") o.machine = v();
    else if (a === "--timeout") o.timeout = Number(v());
    else if (a.startsWith("--")) throw new Error(`unknown option ${a}`);
    else pos.push(a);
  }
  if (pos.length !== 1) throw new Error("usage: opcua_results_client.js ENDPOINT_URL …");
  o.endpoint = pos[0];
  return o;
}

const URI = {
  ua: "http://opcfoundation.org/UA/",
  di: "http://opcfoundation.org/UA/DI/",
  machinery: "http://opcfoundation.org/UA/Machinery/",
  result: "http://opcfoundation.org/UA/Machinery/Result/",
};

async function main() {
  const opcua = loadOpcua();
  const {
    OPCUAClient, MessageSecurityMode, SecurityPolicy, UserTokenType, AttributeIds, DataType,
    Variant, BrowseDirection, NodeClass, ClientSubscription, ClientMonitoredItem,
    TimestampsToReturn, constructEventFilter, OPCUACertificateManager, AddressSpace,
    generateAddressSpace, nodesets, resolveNodeId, coerceNodeId,
  } = opcua;
  const opts = parseArgs(process.argv.slice(2));
  const timer = setTimeout(() => { emit({ ok: false, error: "timeout" }); process.exit(2); },
    opts.timeout);

  const official = AddressSpace.create();
  const pki = fs.mkdtempSync(path.join(os.tmpdir(), "rumba-results-pki-"));
  const certificateManager = new OPCUACertificateManager({ rootFolder: pki, automaticallyAcceptUnknownCertificate: true });
  const secure = opts.security !== "none";
  const client = OPCUAClient.create({
    applicationName: "rumba-results-peer", applicationUri: opts.appUri,
    securityMode: secure ? MessageSecurityMode.SignAndEncrypt : MessageSecurityMode.None,
    securityPolicy: secure ? SecurityPolicy.Basic256Sha256 : SecurityPolicy.None,
    certificateFile: opts.cert, privateKeyFile: opts.key, clientCertificateManager: certificateManager,
    endpointMustExist: false, connectionStrategy: { maxRetry: 0, initialDelay: 100, maxDelay: 200 },
  });
  let session;
  try {
    await client.connect(opts.endpoint);
    session = await client.createSession(opts.user
      ? { type: UserTokenType.UserName, userName: opts.user, password: opts.password }
      : { type: UserTokenType.Anonymous });
    // the official nodesets, loaded locally: what every node on the server is checked against
    await generateAddressSpace(official, [nodesets.standard, nodesets.di, nodesets.ia,
      nodesets.machinery, nodesets.machineryResult]);
    const offNs = (uri) => official.getNamespaceIndex(uri);
    const officialType = (uri, id) => official.findNode(coerceNodeId(`ns=${offNs(uri)};i=${id}`));
    const nsArray = (await session.read({ nodeId: "ns=0;i=2255", attributeId: AttributeIds.Value })).value.value;
    const ns = {};
    for (const [k, uri] of Object.entries(URI)) {
      ns[k] = nsArray.indexOf(uri);
      if (ns[k] < 0) throw new Error(`namespace ${uri} not on the server`);
    }
    // server NodeId of an official type -> the official node, compared by namespace URI + id
    const mismatches = [];
    const checked = [];
    async function typeOf(nodeId) {
      const r = await session.browse({ nodeId, browseDirection: BrowseDirection.Forward,
        referenceTypeId: "HasTypeDefinition", includeSubtypes: true, resultMask: 63 });
      return r.references[0] ? r.references[0].nodeId : null;
    }
    async function expectType(what, nodeId, uriKey, id) {
      const t = await typeOf(nodeId);
      const want = officialType(URI[uriKey], id);
      const got = t && t.namespace === ns[uriKey] && t.value === id;
      const name = (await session.read({ nodeId: t, attributeId: AttributeIds.BrowseName })).value.value;
      checked.push(what);
      if (!got || !want || name.name !== want.browseName.name) {
        mismatches.push({ what, got: t && t.toString(), want: want && want.browseName.toString() });
      }
    }
    async function children(nodeId) {
      const r = await session.browse({ nodeId, browseDirection: BrowseDirection.Forward,
        referenceTypeId: "HierarchicalReferences", includeSubtypes: true, resultMask: 63 });
      return r.references;
    }
    const child = async (nodeId, nsIdx, name) => {
      const c = (await children(nodeId)).find((r) => r.browseName.name === name && r.browseName.namespaceIndex === nsIdx);
      if (!c) throw new Error(`${nodeId.toString()} has no ${nsIdx}:${name}`);
      return c.nodeId;
    };
    const value = async (nodeId) => (await session.read({ nodeId, attributeId: AttributeIds.Value })).value.value;

    const machinesFolder = coerceNodeId(`ns=${ns.machinery};i=1001`);
    const machines = (await children(machinesFolder)).filter((r) => r.nodeClass === NodeClass.Object);
    const out = { machines: {} };
    for (const m of machines) {
      const name = m.browseName.name;
      const ident = await child(m.nodeId, ns.di, "Identification");
      await expectType(`${name}/Identification`, ident, "machinery", 1012);
      const idv = {};
      for (const r of await children(ident)) {
        const v = await value(r.nodeId);
        idv[r.browseName.name] = v && v.text !== undefined ? v.text : v;
      }
      // every mandatory property of the official MachineIdentificationType is on the instance
      const offIdent = officialType(URI.machinery, 1012);
      const mandatory = [];
      for (let t = offIdent; t; t = t.subtypeOfObj) {
        for (const c of t.getAggregates()) {
          if (c.modellingRule === "Mandatory") mandatory.push(c.browseName.name);
        }
      }
      const missing = mandatory.filter((n) => !(n in idv));
      if (missing.length) mismatches.push({ what: `${name}/Identification`, missing });
      const bb = await child(m.nodeId, ns.machinery, "MachineryBuildingBlocks");
      await expectType(`${name}/MachineryBuildingBlocks`, bb, "ua", 61);
      const itemState = await child(bb, ns.machinery, "MachineryItemState");
      await expectType(`${name}/MachineryItemState`, itemState, "machinery", 1002);
      const rm = await child(bb, ns.result, "ResultManagement");
      await expectType(`${name}/ResultManagement`, rm, "result", 1004);
      const transfer = await child(rm, ns.result, "ResultTransfer");
      await expectType(`${name}/ResultTransfer`, transfer, "result", 1003);
      const methods = {};
      for (const mname of ["GetLatestResult", "GetResultById", "GetResultIdListFiltered"]) {
        methods[mname] = await child(rm, ns.result, mname);
      }
      const state = {
        itemState: (await value(await child(itemState, 0, "CurrentState"))).text,
      };
      const check = (await children(m.nodeId)).find((r) => r.browseName.name === "Check");
      for (const r of await children(check.nodeId)) {
        const v = await value(r.nodeId);
        state[r.browseName.name] = v instanceof Date ? v.toISOString() : v;
      }
      out.machines[name] = { identification: idv, state, rm, methods, transfer, itemStateNode: itemState };
    }
    if (mismatches.length) throw new Error(`not of the official type: ${JSON.stringify(mismatches)}`);
    const mname = opts.machine || Object.keys(out.machines)[0];
    const M = out.machines[mname];
    const call = async (method, inputArguments) => {
      const r = await session.call({ objectId: M.rm, methodId: M.methods[method], inputArguments });
      if (!r.statusCode.isGood()) throw new Error(`${method}: ${r.statusCode.toString()}`);
      return r.outputArguments.map((a) => a.value);
    };
    const meta = (res) => {
      const md = res.resultMetaData;
      return { resultId: md.resultId, resultState: md.resultState, evaluation: md.resultEvaluation,
        creationTime: md.creationTime && md.creationTime.toISOString(),
        hasFile: md.hasTransferableDataOnFile,
        content: (res.resultContent || []).map((v) => {
          const kv = v.value;
          const [val, u, eu] = kv.value.value.map((x) => x.value);
          return { key: kv.key.name, value: val, u: Number.isNaN(u) ? null : u,
            unit: eu.displayName.text, unitId: eu.unitId };
        }) };
    };

    let eventSeen = null;
    const seen = [];
    if (opts.waitEvent) {
      const sub = ClientSubscription.create(session, { requestedPublishingInterval: 50,
        requestedLifetimeCount: 1000, requestedMaxKeepAliveCount: 10, maxNotificationsPerPublish: 100,
        publishingEnabled: true, priority: 1 });
      const filter = constructEventFilter(["EventType", "SourceNode", "Message", `${ns.result}:Result`]);
      const item = ClientMonitoredItem.create(sub, { nodeId: "ns=0;i=2253", attributeId: AttributeIds.EventNotifier },
        { samplingInterval: 0, discardOldest: true, queueSize: 100, filter }, TimestampsToReturn.Both);
      eventSeen = new Promise((resolve) => {
        item.on("changed", (fields) => {
          const t = fields[0].value;
          if (t && t.namespace === ns.result && t.value === 1002) {
            resolve({ message: fields[2].value.text, result: meta(fields[3].value) });
          }
        });
      });
      await new Promise((r) => item.once("initialized", r));
      // the check's state while the run goes on: every State and DoneTouches change seen
      const check0 = (await children((await children(machinesFolder))
        .find((r) => r.browseName.name === mname).nodeId)).find((r) => r.browseName.name === "Check");
      const ready = [];  // every monitored item live before the test is told to run
      for (const r of await children(check0.nodeId)) {
        if (!["State", "DoneTouches", "TotalTouches", "RunId"].includes(r.browseName.name)) continue;
        const mi = ClientMonitoredItem.create(sub, { nodeId: r.nodeId, attributeId: AttributeIds.Value },
          { samplingInterval: 0, discardOldest: false, queueSize: 1000 }, TimestampsToReturn.Both);
        mi.on("changed", (dv) => seen.push([r.browseName.name, dv.value.value]));
        ready.push(new Promise((res) => mi.once("initialized", res)));
      }
      const itemStateNode = await child(M.itemStateNode, 0, "CurrentState");
      const mi = ClientMonitoredItem.create(sub, { nodeId: itemStateNode, attributeId: AttributeIds.Value },
        { samplingInterval: 0, discardOldest: false, queueSize: 1000 }, TimestampsToReturn.Both);
      mi.on("changed", (dv) => seen.push(["MachineryItemState", dv.value.value && dv.value.value.text]));
      ready.push(new Promise((res) => mi.once("initialized", res)));
      await Promise.all(ready);
      emit({ event: "subscribed", state: M.state });
    }
    const ev = eventSeen ? await eventSeen : null;
    // the state after the event, as a dashboard polling after the run would read it
    const check = (await children(coerceNodeId((await children(machinesFolder))
      .find((r) => r.browseName.name === mname).nodeId))).find((r) => r.browseName.name === "Check");
    const after = {};
    for (const r of await children(check.nodeId)) {
      const v = await value(r.nodeId);
      after[r.browseName.name] = v instanceof Date ? v.toISOString() : v;
    }
    const timeout = { dataType: DataType.Double, value: 5000 };
    const [, latest, latestErr] = await call("GetLatestResult", [timeout]);
    const [, all, allErr] = await call("GetResultIdListFiltered", [
      { dataType: DataType.ExtensionObject, value: new opcua.ContentFilter({ elements: [] }) },
      { dataType: DataType.ExtensionObject, arrayType: opcua.VariantArrayType.Array, value: [] },
      { dataType: DataType.UInt32, value: 0 }, timeout]);
    const byId = {};
    for (const id of (opts.ids.length ? opts.ids : all)) {
      const [, res, err] = await call("GetResultById", [{ dataType: DataType.String, value: id }, timeout]);
      byId[id] = { error: err, ...meta(res) };
    }
    // filtered by the spec's own field: every result not decidable within its uncertainty
    const ndFilter = new opcua.ContentFilter({ elements: [{
      filterOperator: opcua.FilterOperator.Equals,
      filterOperands: [
        new opcua.SimpleAttributeOperand({ typeDefinitionId: coerceNodeId(`ns=${ns.result};i=2001`),
          browsePath: [{ namespaceIndex: ns.result, name: "ResultMetaData" }, { namespaceIndex: ns.result, name: "ResultEvaluation" }],
          attributeId: AttributeIds.Value }),
        new opcua.LiteralOperand({ value: { dataType: DataType.Int32, value: 3 } })] }] });
    const [, nd, ndErr] = await call("GetResultIdListFiltered", [
      { dataType: DataType.ExtensionObject, value: ndFilter },
      { dataType: DataType.ExtensionObject, arrayType: opcua.VariantArrayType.Array, value: [] },
      { dataType: DataType.UInt32, value: 0 }, timeout]);
    let download = null;
    if (opts.download) {
      const gen = await child(M.transfer, 0, "GenerateFileForRead");
      // ResultTransferOptionsDataType (its only field, ResultId, from the abstract base type):
      // node-opcua 2.182 does not build subtypes of a structure with fields, so the body is
      // encoded here as OPC 10000-6 §5.2.2.4 says: Int32 length + UTF-8, under the type's
      // official DefaultBinary encoding id (ns=Result;i=5001)
      const { OpaqueStructure } = require(require.resolve("node-opcua-extension-object",
        { paths: [path.dirname(require.resolve("node-opcua", { paths: [process.env.RUMBA_NODE_PEERS || path.join(__dirname, "..", "..", ".peers", "node")] }))] }));
      const id = Buffer.from(opts.download, "utf8");
      const body = Buffer.alloc(4 + id.length);
      body.writeInt32LE(id.length, 0);
      id.copy(body, 4);
      const dtf = new OpaqueStructure(coerceNodeId(`ns=${ns.result};i=5001`), body);
      const r = await session.call({ objectId: M.transfer, methodId: gen, inputArguments: [
        { dataType: DataType.ExtensionObject, value: dtf }] });
      if (!r.statusCode.isGood()) throw new Error(`GenerateFileForRead: ${r.statusCode.toString()}`);
      const fileNode = r.outputArguments[0].value;
      const handle = r.outputArguments[1].value;
      const typeOk = (await typeOf(fileNode)).toString() === "ns=0;i=11575";
      const readM = await child(fileNode, 0, "Read");
      const closeM = await child(fileNode, 0, "Close");
      const sz = await value(await child(fileNode, 0, "Size"));
      const size = Array.isArray(sz) ? sz[0] * 2 ** 32 + sz[1] : Number(sz);  // UInt64: [high, low]
      const parts = [];
      for (;;) {
        const rr = await session.call({ objectId: fileNode, methodId: readM, inputArguments: [
          { dataType: DataType.UInt32, value: handle }, { dataType: DataType.Int32, value: 65536 }] });
        if (!rr.statusCode.isGood()) throw new Error(`Read: ${rr.statusCode.toString()}`);
        const chunk = rr.outputArguments[0].value;
        if (!chunk || chunk.length === 0) break;
        parts.push(Buffer.from(chunk));
      }
      const cr = await session.call({ objectId: fileNode, methodId: closeM, inputArguments: [
        { dataType: DataType.UInt32, value: handle }] });
      const data = Buffer.concat(parts);
      download = { bytes: data.length, size, fileType: typeOk, closed: cr.statusCode.isGood(),
        sha256: crypto.createHash("sha256").update(data).digest("hex"), head: data.subarray(0, 5).toString("latin1") };
    }
    for (const m of Object.values(out.machines)) {
      delete m.rm; delete m.methods; delete m.transfer; delete m.itemStateNode;
    }
    emit({ ok: true, checked, machines: out.machines, event: ev, after, seen,
      latest: { error: latestErr, ...meta(latest) }, all, allErr, byId, notDecidable: nd, ndErr, download });
    return 0;
  } catch (e) {
    emit({ ok: false, error: e.message, stack: String(e.stack).split("\n").slice(0, 4).join(" | ") });
    return 2;
  } finally {
    try { if (session) await session.close(); } catch (_) { /* ignore */ }
    try { await client.disconnect(); } catch (_) { /* ignore */ }
    try { await certificateManager.dispose(); } catch (_) { /* ignore */ }
    try { official.dispose(); } catch (_) { /* ignore */ }
    fs.rmSync(pki, { recursive: true, force: true });
    clearTimeout(timer);
  }
}
main().then((code) => process.exit(code));
