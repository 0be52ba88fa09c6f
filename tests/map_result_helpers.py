"""A journaled map result for the surface tests (history, HMI, fleet store, OPC UA, AQDEF):
the small two-placement map of tests/test_map_cli.py fitted once, with its report, judged by the
daemon.yaml's volumetric limit and journaled by ``rumba map --store``."""

from __future__ import annotations

from pathlib import Path

from benchmarks.rigs.daemon_helpers import write_daemon_yaml
from tests.test_map_cli import MACHINE, run_cli


def journaled_map(tmp: Path, out: dict, *, limit: str = "{warn: 5, fail: 400}") -> tuple:
    """(daemon.yaml, the map JSON, the report dir, stdout) of ``rumba map … --store``; the
    machine ``mill1``'s volumetric limit is ``limit`` (the default warns: the fixture's map has
    a volumetric max of some ten µm)."""
    cfg = write_daemon_yaml(tmp)
    text = cfg.read_text().replace("volumetric_max_um: {warn: 200, fail: 400}",
                                   f"volumetric_max_um: {limit}")
    cfg.write_text(text)
    code, so, se = run_cli(["map", "--machine", str(MACHINE), "--placement", *out[0],
                            "--placement", *out[1], "--max-degree", "2", "--config", str(cfg),
                            "--json", str(tmp / "m.json"), "--report", str(tmp / "rep"),
                            "--store"])
    assert code == 0, se
    return cfg, tmp / "m.json", tmp / "rep", so
