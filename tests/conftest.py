"""Shared pytest hooks: in CI (RUMBA_REQUIRE_PEERS=1) a peer test may not pass by skipping."""

from __future__ import annotations

import os

# Small dense problems: BLAS threads only contend on a 2-core machine (as daemon/__init__.py).
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import pytest  # noqa: E402


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo):  # type: ignore[no-untyped-def]
    outcome = yield
    report = outcome.get_result()
    required = os.environ.get("RUMBA_REQUIRE_PEERS") == "1"
    needs_peer = item.get_closest_marker("peer") or item.get_closest_marker("linuxcnc")
    if required and needs_peer and report.skipped:
        # .ci/run installed the peers: a skip here means the peer is broken, not absent.
        report.outcome = "failed"
        report.longrepr = f"peer test skipped in CI (RUMBA_REQUIRE_PEERS=1): {report.longrepr}"
