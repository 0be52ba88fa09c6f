"""The dependency direction of DESIGN.md, checked on every import statement (lazy ones too).

`identification` imports nothing of ours; `drivers` and `simulators` never import the daemon's
application (program generator, sessions, store, CLI) — only its data contracts, leaf modules
that themselves import nothing but `identification`; the daemon imports the simulator only in
its demo and ``rumba sim`` entry points.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
OURS = ("identification", "daemon", "drivers", "simulators")
CONTRACTS = {"daemon.messages", "daemon.config", "daemon.config_yaml", "daemon.probelog",
             "daemon.touch_centres"}
# what simulator front-ends share with the links (they speak what drivers/ speak)
PROTOCOL_TABLES = {"drivers.opcua_space", "drivers.modbus_map", "drivers.opcua_certs",
                   "drivers.can_panel"}
DAEMON_SIM_ENTRY_POINTS = {"daemon.demo_e2e", "daemon.demo_linuxcnc", "daemon.commands.sim"}


def _module(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


def _imports(path: Path) -> set[str]:
    """Every module of ours that ``path`` imports, at any depth of the file."""
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            # ``from daemon import dialects`` imports daemon.dialects
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        else:
            continue
        out.update(n for n in names if n.split(".")[0] in OURS)
    return out


def _graph() -> dict[str, set[str]]:
    files = [p for pkg in OURS for p in (ROOT / pkg).rglob("*.py")]
    mods = {_module(p): p for p in files}
    # keep only names that are modules (``from drivers.base import LinkError`` → drivers.base)
    return {m: {i for i in _imports(p) if i in mods} for m, p in mods.items()}


GRAPH = _graph()


def _violations(rule) -> list[str]:
    return sorted(f"{m} imports {i}" for m, deps in GRAPH.items() for i in deps
                  if not rule(m, i))


def _pkg(name: str) -> str:
    return name.split(".")[0]


def test_the_graph_is_not_empty():
    # a broken walker (wrong root, wrong suffix) would make every rule below pass vacuously
    assert len(GRAPH) > 60
    assert "daemon.messages" in GRAPH["drivers.base"]
    assert "identification.kinematics" in GRAPH["simulators.truth"]


def test_identification_imports_nothing_of_ours():
    assert _violations(lambda m, i: _pkg(m) != "identification"
                       or _pkg(i) == "identification") == []


def test_contracts_are_leaves_over_identification():
    assert _violations(lambda m, i: m not in CONTRACTS
                       or i in CONTRACTS or _pkg(i) == "identification"
                       or i == "daemon") == []


@pytest.mark.parametrize("pkg", ["drivers", "simulators"])
def test_links_and_simulator_use_only_the_daemons_contracts(pkg):
    assert _violations(lambda m, i: _pkg(m) != pkg or _pkg(i) != "daemon"
                       or i in CONTRACTS or i == "daemon") == []


def test_drivers_never_import_the_simulator():
    assert _violations(lambda m, i: _pkg(m) != "drivers" or _pkg(i) != "simulators") == []


def test_simulator_uses_only_the_protocol_tables_of_drivers():
    assert _violations(lambda m, i: _pkg(m) != "simulators" or _pkg(i) != "drivers"
                       or i in PROTOCOL_TABLES or i == "drivers") == []


def test_daemon_imports_the_simulator_only_in_demo_entry_points():
    assert _violations(lambda m, i: _pkg(m) != "daemon" or _pkg(i) != "simulators"
                       or m in DAEMON_SIM_ENTRY_POINTS) == []
