"""OPC UA results server: 1 000 stored results listed and filtered through
GetResultIdListFiltered, and one GetResultById, timed from an asyncua client over
Basic256Sha256 SignAndEncrypt on loopback. Target: list and filter 1 000 results in < 1 s."""

# .venv/bin/python -m benchmarks.bench_opcua_results [--results 1000] [--runs 5]
#
# Needs the official nodesets (bash .ci/install-peers.sh node-opcua). Median and best of
# --runs calls each, after one untimed call (the client's first call pays its type loading).

from __future__ import annotations

import argparse
import asyncio
import statistics
import tempfile
import time
from pathlib import Path


async def main(n: int, runs: int) -> None:
    from asyncua import Client, ua

    from benchmarks.rigs.opcua_results_helpers import (
        CLIENT_URI,
        PASSWORD,
        USER,
        fill,
        make_pki,
        server_config,
    )
    from daemon.opcua.server import ResultServer
    from daemon.store.journal import Store

    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        store = Store(tmp / "journal.sqlite", "NORMAL")
        fill(store, extra=n - 5)  # the 5 verdict cases + the rest: n results
        cert, key, _ = await make_pki(tmp)
        srv = ResultServer(server_config(tmp, cert.parent), store, ["mill1"])
        t0 = time.perf_counter()
        url = await srv.start()
        print(f"server start (4 official nodesets loaded): {time.perf_counter() - t0:.1f} s")
        c = Client(url, timeout=30)
        c.application_uri = CLIENT_URI
        await c.set_security_string(f"Basic256Sha256,SignAndEncrypt,{cert},{key}")
        c.set_user(USER)
        c.set_password(PASSWORD)
        try:
            async with c:
                ns = await c.get_namespace_array()
                res = ns.index("http://opcfoundation.org/UA/Machinery/Result/")
                rm = c.get_node(ua.NodeId("mill1.ResultManagement",
                                          ns.index("urn:rumba-cnc:results")))
                t = ua.Variant(5000.0, ua.VariantType.Double)
                none = ua.Variant([], ua.VariantType.ExtensionObject)
                allv = ua.Variant(0, ua.VariantType.UInt32)
                not_ok = ua.ContentFilter(Elements=[ua.ContentFilterElement(
                    FilterOperator=ua.FilterOperator.Equals, FilterOperands=[
                        ua.SimpleAttributeOperand(BrowsePath=[
                            ua.QualifiedName("ResultMetaData", res),
                            ua.QualifiedName("ResultEvaluation", res)],
                            AttributeId=ua.AttributeIds.Value),
                        ua.LiteralOperand(Value=ua.Variant(2))])])
                cases = {
                    "list all": (f"{res}:GetResultIdListFiltered",
                                 [ua.Variant(ua.ContentFilter()), none, allv, t]),
                    "filter NotOK": (f"{res}:GetResultIdListFiltered",
                                     [ua.Variant(not_ok), none, allv, t]),
                    "GetResultById": (f"{res}:GetResultById", [ua.Variant("run-nd"), t]),
                }
                for name, (method, args) in cases.items():
                    out = await rm.call_method(method, *args)
                    times = []
                    for _ in range(runs):
                        t1 = time.perf_counter()
                        out = await rm.call_method(method, *args)
                        times.append(time.perf_counter() - t1)
                    size = len(out[1]) if isinstance(out[1], list) else 1
                    print(f"{name:14s} {size:5d} ids  median {statistics.median(times):.3f} s"
                          f"  best {min(times):.3f} s  (N = {runs})")
        finally:
            await srv.stop()
            store.close()


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--results", type=int, default=1000)
    ap.add_argument("--runs", type=int, default=5)
    a = ap.parse_args()
    asyncio.run(main(a.results, a.runs))
