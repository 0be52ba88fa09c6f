#!/usr/bin/env node
// Independent OPC UA client (node-opcua) for interoperability tests: reads one node, prints JSON.
//
//   node tests/peers/opcua_client.js ENDPOINT_URL NODE_ID [--secure] [--user U --password P]
//                                    [--timeout MS]
//
//   --secure     Basic256Sha256 + SignAndEncrypt (default: SecurityPolicy None, mode None)
//   --user/--password  username identity token (also RUMBA_OPCUA_USER / RUMBA_OPCUA_PASSWORD);
//                anonymous otherwise
//   RUMBA_OPCUA_PKI_DIR  the client's certificate folder (own/, trusted/, rejected/ …), e.g.
//                under the test's temp dir; its self-signed certificate is made there on first
//                use. Unset: a fresh folder under os.tmpdir(), removed at exit. Never the
//                default ~/.config/node-opcua-default-nodejs.
//   RUMBA_NODE_PEERS     folder holding node_modules/node-opcua (default: <repo>/.peers/node,
//                installed by `bash .ci/install-peers.sh node-opcua`)
//
// Output (stdout, one line): {"ok":true,"nodeId":…,"statusCode":"Good","dataType":"Double",
//   "arrayType":"Scalar","value":…,"sourceTimestamp":…,"serverTimestamp":…,
//   "securityPolicy":…,"securityMode":…}. Int64/UInt64 values are decimal strings.
// Exit status: 0 Good, 1 read answered with a bad status, 2 usage / connection / session error
// (then {"ok":false,"error":…}).
"use strict";
const fs = require("fs");
const os = require("os");
const path = require("path");

// stdout carries exactly one JSON line: node-opcua's own messages ("Creating default
// certificate ... please wait", warnings) go through console.* and are sent to stderr.
const emit = (obj) => process.stdout.write(`${JSON.stringify(obj)}\n`);
for (const k of ["log", "info", "warn", "debug"]) {
  console[k] = (...a) => process.stderr.write(`${a.map(String).join(" ")}\n`);
}

function loadOpcua() {
  const roots = [process.env.RUMBA_NODE_PEERS, path.join(__dirname, "..", "..", ".peers", "node")];
  for (const root of roots.filter(Boolean)) {
    try {
      return require(require.resolve("node-opcua", { paths: [root] }));
    } catch (_) {
      /* try the next one */
    }
  }
  return require("node-opcua");
}

function parseArgs(argv) {
  const opts = { secure: false, user: process.env.RUMBA_OPCUA_USER, timeout: 10000 };
  opts.password = process.env.RUMBA_OPCUA_PASSWORD;
  const pos = [];
  for (let i = 0; i < argv.length; i++) {
    const a = argv[i];
    if (a === "--secure") opts.secure = true;
    else if (a === "--user") opts.user = argv[++i];
    else if (a === "--password") opts.password = argv[++i];
    else if (a === "--timeout") opts.timeout = Number(argv[++i]);
    else if (a.startsWith("--")) throw new Error(`unknown option ${a}`);
    else pos.push(a);
  }
  if (pos.length !== 2) throw new Error("usage: opcua_client.js ENDPOINT_URL NODE_ID [--secure] [--user U --password P]");
  [opts.endpoint, opts.nodeId] = pos;
  return opts;
}

function jsonValue(value, dataTypeName) {
  // node-opcua gives Int64/UInt64 as [high, low] 32-bit words
  const big = (hl) => ((BigInt(hl[0] >>> 0) << 32n) | BigInt(hl[1] >>> 0));
  const int64 = (hl) => {
    let v = big(hl);
    if (dataTypeName === "Int64" && v >= 1n << 63n) v -= 1n << 64n;
    return v.toString();
  };
  if ((dataTypeName === "Int64" || dataTypeName === "UInt64") && Array.isArray(value)) {
    return Array.isArray(value[0]) ? value.map(int64) : int64(value);
  }
  if (ArrayBuffer.isView(value)) return Array.from(value);
  if (Buffer.isBuffer(value)) return value.toString("base64");
  if (value && typeof value === "object" && typeof value.toJSON === "function") return value.toJSON();
  if (value && typeof value === "object" && "text" in value) return value.text; // LocalizedText
  return value;
}

async function main() {
  let opts;
  try {
    opts = parseArgs(process.argv.slice(2));
  } catch (e) {
    emit({ ok: false, error: e.message });
    return 2;
  }
  const opcua = loadOpcua();
  const { OPCUAClient, OPCUACertificateManager, MessageSecurityMode, SecurityPolicy,
    UserTokenType, AttributeIds, DataType, VariantArrayType } = opcua;

  let pkiDir = process.env.RUMBA_OPCUA_PKI_DIR;
  let ownTemp = null;
  if (!pkiDir) {
    ownTemp = fs.mkdtempSync(path.join(os.tmpdir(), "rumba-opcua-pki-"));
    pkiDir = ownTemp;
  }
  fs.mkdirSync(pkiDir, { recursive: true });
  const certificateManager = new OPCUACertificateManager({
    rootFolder: pkiDir,
    automaticallyAcceptUnknownCertificate: true, // test peer: trust the server under test
  });

  const client = OPCUAClient.create({
    applicationName: "rumba-peer-node-opcua",
    applicationUri: `urn:${os.hostname()}:rumba-peer-node-opcua`,
    clientCertificateManager: certificateManager,
    securityMode: opts.secure ? MessageSecurityMode.SignAndEncrypt : MessageSecurityMode.None,
    securityPolicy: opts.secure ? SecurityPolicy.Basic256Sha256 : SecurityPolicy.None,
    endpointMustExist: false,
    connectionStrategy: { maxRetry: 0, initialDelay: 100, maxDelay: 200 },
    requestedSessionTimeout: opts.timeout,
    defaultTransactionTimeout: opts.timeout,
  });

  let session = null;
  let code = 2;
  const timer = setTimeout(() => {
    emit({ ok: false, error: `timeout after ${opts.timeout} ms` });
    process.exit(2);
  }, opts.timeout + 2000);
  try {
    await client.connect(opts.endpoint);
    const identity = opts.user
      ? { type: UserTokenType.UserName, userName: opts.user, password: opts.password || "" }
      : { type: UserTokenType.Anonymous };
    session = await client.createSession(identity);
    const dv = await session.read({ nodeId: opts.nodeId, attributeId: AttributeIds.Value });
    const good = dv.statusCode.isGood();
    const v = dv.value || {};
    const dataType = DataType[v.dataType];
    emit({
      ok: good,
      endpoint: opts.endpoint,
      nodeId: opts.nodeId,
      statusCode: dv.statusCode.name,
      dataType,
      arrayType: VariantArrayType[v.arrayType],
      value: good ? jsonValue(v.value, dataType) : null,
      sourceTimestamp: dv.sourceTimestamp ? dv.sourceTimestamp.toISOString() : null,
      serverTimestamp: dv.serverTimestamp ? dv.serverTimestamp.toISOString() : null,
      securityPolicy: opts.secure ? "Basic256Sha256" : "None",
      securityMode: opts.secure ? "SignAndEncrypt" : "None",
    });
    code = good ? 0 : 1;
  } catch (e) {
    emit({ ok: false, endpoint: opts.endpoint, nodeId: opts.nodeId, error: e.message });
    code = 2;
  } finally {
    try {
      if (session) await session.close();
    } catch (_) { /* ignore */ }
    try {
      await client.disconnect();
    } catch (_) { /* ignore */ }
    try {
      await certificateManager.dispose();
    } catch (_) { /* ignore */ }
    if (ownTemp) fs.rmSync(ownTemp, { recursive: true, force: true });
    clearTimeout(timer);
  }
  return code;
}

main().then((code) => process.exit(code));
