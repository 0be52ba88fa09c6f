#!/usr/bin/env node
// Independent OPC UA client (node-opcua) exercising the rumba address space: read, subscribe,
// write, call a method.  Used by tests/test_transport_opcua.py (peer tests).
//
//   node tests/peers/opcua_rumba_session.js ENDPOINT_URL [--secure] [--user U --password P]
//
// stdout: JSON lines. First {"event":"subscribed"} once the monitored item on the start request
// (R[u1,1]) is live — the test then raises the request on the simulated CNC — and at the end
// {"ok":true,"state":…,"sawRequest":true,"abortCalled":true,"busyWritten":true}.
// RUMBA_OPCUA_PKI_DIR: certificate folder for the client (under the test's temp dir).
"use strict";
const fs = require("fs");
const os = require("os");
const path = require("path");

const emit = (obj) => process.stdout.write(`${JSON.stringify(obj)}\n`);
for (const k of ["log", "info", "warn", "debug"]) {
  console[k] = (...a) => process.stderr.write(`${a.map(String).join(" ")}\n`);
}
const roots = [process.env.RUMBA_NODE_PEERS, path.join(__dirname, "..", "..", ".peers", "node")];
let opcua = null;
for (const root of roots.filter(Boolean)) {
  try { opcua = require(require.resolve("node-opcua", { paths: [root] })); break; } catch (_) { /* next */ }
}
opcua = opcua || require("node-opcua");
const { OPCUAClient, OPCUACertificateManager, MessageSecurityMode, SecurityPolicy, UserTokenType,
  AttributeIds, DataType, ClientSubscription, ClientMonitoredItem, TimestampsToReturn } = opcua;

const NS_URI = "urn:rumba-cnc:cnc";
const args = process.argv.slice(2);
const opts = { secure: false, endpoint: null, user: null, password: null };
for (let i = 0; i < args.length; i++) {
  if (args[i] === "--secure") opts.secure = true;
  else if (args[i] === "--user") opts.user = args[++i];
  else if (args[i] === "--password") opts.password = args[++i];
  else opts.endpoint = args[i];
}

async function main() {
  const pkiDir = process.env.RUMBA_OPCUA_PKI_DIR || fs.mkdtempSync(path.join(os.tmpdir(), "rumba-pki-"));
  fs.mkdirSync(pkiDir, { recursive: true });
  const certificateManager = new OPCUACertificateManager({
    rootFolder: pkiDir, automaticallyAcceptUnknownCertificate: true,
  });
  const client = OPCUAClient.create({
    applicationName: "rumba-peer-node-opcua",
    applicationUri: `urn:${os.hostname()}:rumba-peer-node-opcua`,
    clientCertificateManager: certificateManager,
    securityMode: opts.secure ? MessageSecurityMode.SignAndEncrypt : MessageSecurityMode.None,
    securityPolicy: opts.secure ? SecurityPolicy.Basic256Sha256 : SecurityPolicy.None,
    endpointMustExist: false,
    connectionStrategy: { maxRetry: 0, initialDelay: 100, maxDelay: 200 },
  });
  const timer = setTimeout(() => { emit({ ok: false, error: "timeout" }); process.exit(2); }, 40000);
  let session = null;
  try {
    await client.connect(opts.endpoint);
    session = await client.createSession(opts.user
      ? { type: UserTokenType.UserName, userName: opts.user, password: opts.password || "" }
      : { type: UserTokenType.Anonymous });
    const nsArray = (await session.read({ nodeId: "ns=0;i=2255", attributeId: AttributeIds.Value })).value.value;
    const ns = nsArray.indexOf(NS_URI);
    if (ns < 0) throw new Error(`namespace ${NS_URI} not on the server`);
    const id = (p) => `ns=${ns};s=${p}`;
    const state = (await session.read({ nodeId: id("/Channel/State/rumbaState"), attributeId: AttributeIds.Value })).value.value;

    const sub = ClientSubscription.create(session, {
      requestedPublishingInterval: 50, requestedLifetimeCount: 100, requestedMaxKeepAliveCount: 10,
      maxNotificationsPerPublish: 100, publishingEnabled: true, priority: 1,
    });
    const item = ClientMonitoredItem.create(sub, { nodeId: id("/Channel/Parameter/R[u1,1]"), attributeId: AttributeIds.Value },
      { samplingInterval: 20, discardOldest: true, queueSize: 10 }, TimestampsToReturn.Both);
    const sawRequest = await new Promise((resolve) => {
      let announced = false;
      item.on("changed", (dv) => {
        if (!announced) { announced = true; emit({ event: "subscribed" }); }
        if (dv.value.value >= 1) resolve(true);
      });
      setTimeout(() => resolve(false), 20000);
    });
    const busy = await session.write({ nodeId: id("/Channel/Parameter/R[u1,2]"), attributeId: AttributeIds.Value,
      value: { value: { dataType: DataType.Double, value: 1.0 } } });
    const call = await session.call({ objectId: id("/Methods"), methodId: id("/Methods/Abort"), inputArguments: [] });
    await sub.terminate();
    emit({ ok: true, state, sawRequest, busyWritten: busy.isGood(), abortCalled: call.statusCode.isGood(),
      securityMode: opts.secure ? "SignAndEncrypt" : "None" });
    return 0;
  } catch (e) {
    emit({ ok: false, error: e.message });
    return 2;
  } finally {
    try { if (session) await session.close(); } catch (_) { /* ignore */ }
    try { await client.disconnect(); } catch (_) { /* ignore */ }
    try { await certificateManager.dispose(); } catch (_) { /* ignore */ }
    clearTimeout(timer);
  }
}
main().then((code) => process.exit(code));
