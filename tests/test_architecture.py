"""The dependency direction of DESIGN.md, checked on every import statement (lazy ones too).

``identification ← contracts ← {programs, drivers, simulators} ← daemon ← {demos, benchmarks}``:
a package imports only packages of a lower layer (and itself); packages of one layer never import
each other; and no module imports itself back through a chain of imports. No exceptions.

Inside ``daemon/`` the rooms (one subpackage per job, a few top-level modules) follow the same
rule with the order of ``ROOMS``: a room imports only rooms of a lower rank (and itself).
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LAYERS = {"identification": 0, "contracts": 1, "programs": 2, "drivers": 2, "simulators": 2,
          "daemon": 3, "demos": 4, "benchmarks": 4}
OURS = tuple(LAYERS)
# bottom → top; rooms of one rank never import each other ("daemon": its __init__)
ROOMS = {"daemon": 0, "safepath": 0, "hosts": 0, "authlimit": 0, "machines": 1, "analysis": 2,
         "store": 3, "compensation": 4, "reports": 5, "mqtt": 5, "notify": 5, "run": 6, "hmi": 7,
         "opcua": 7, "fleet": 8, "config": 9, "service": 10, "cli": 11}


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
            # ``from programs import dialects`` imports programs.dialects
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        else:
            continue
        out.update(n for n in names if n.split(".")[0] in OURS)
    return out


def _graph() -> dict[str, set[str]]:
    files = [p for pkg in OURS for p in (ROOT / pkg).rglob("*.py")]
    mods = {_module(p): p for p in files}
    # keep only names that are modules (``from drivers.base import LinkError`` → drivers.base)
    return {m: {i for i in _imports(p) if i in mods and i != m} for m, p in mods.items()}


GRAPH = _graph()


def _pkg(name: str) -> str:
    return name.split(".")[0]


def test_the_graph_is_not_empty():
    # a broken walker (wrong root, wrong suffix) would make every rule below pass vacuously
    assert len(GRAPH) > 80
    assert "contracts.messages" in GRAPH["drivers.base"]
    assert "identification.kinematics" in GRAPH["simulators.truth"]
    assert {_pkg(m) for m in GRAPH} == set(LAYERS)


def test_every_import_points_down_the_layers():
    bad = sorted(f"{m} imports {i}" for m, deps in GRAPH.items() for i in deps
                 if _pkg(i) != _pkg(m) and LAYERS[_pkg(i)] >= LAYERS[_pkg(m)])
    assert bad == []


def _room(name: str) -> str:
    parts = name.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


def _upward_in_daemon(graph: dict[str, set[str]]) -> list[str]:
    return sorted(f"{m} imports {i}" for m, deps in graph.items() for i in deps
                  if _pkg(m) == _pkg(i) == "daemon" and _room(i) != _room(m)
                  and ROOMS[_room(i)] >= ROOMS[_room(m)])


def test_every_daemon_module_is_in_a_room():
    assert sorted({_room(m) for m in GRAPH if _pkg(m) == "daemon"} - set(ROOMS)) == []
    assert set(ROOMS) <= {_room(m) for m in GRAPH if _pkg(m) == "daemon"}


def test_every_import_in_the_daemon_points_down_the_rooms():
    assert _upward_in_daemon(GRAPH) == []


def test_an_upward_import_between_rooms_is_caught():
    # the store journal importing the session (lazily or not), or two rooms of one rank
    assert "daemon.store.journal" in GRAPH and "daemon.run.session" in GRAPH
    graph = {m: set(deps) for m, deps in GRAPH.items()}
    graph["daemon.store.journal"].add("daemon.run.session")
    graph["daemon.mqtt.publisher"].add("daemon.notify.notifier")
    assert _upward_in_daemon(graph) == [
        "daemon.mqtt.publisher imports daemon.notify.notifier",
        "daemon.store.journal imports daemon.run.session"]


def test_a_lazy_import_is_in_the_graph():
    # imports inside functions count: the report job imports the report only when a run gets
    # there (daemon/run/report_job.py, no longer the session itself)
    assert "daemon.reports.report" in GRAPH["daemon.run.report_job"]


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on: set[str] = set()
    stack: list[str] = []
    out: list[list[str]] = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in on:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return out


def test_no_import_circle():
    assert _cycles(GRAPH) == []


def test_the_cycle_finder_sees_a_planted_circle():
    graph = {m: set(deps) for m, deps in GRAPH.items()}
    graph["identification.model"].add("identification.kinematics")
    graph["identification.kinematics"].add("identification.model")
    assert ["identification.kinematics", "identification.model"] in _cycles(graph)


# The project's history lives in git: code, configuration and their comments say what and why,
# never which issue asked for it ("(issue 22)", "issue 24 item 5: …"). Upstream trackers are
# cited with their '#' (LinuxCNC's "#3650"), which this does not match.
ISSUE_CITE = re.compile(r"\bissues? \d+|\bissue-\d+", re.I)
CITE_SUFFIXES = {".py", ".yaml", ".yml", ".js", ".css", ".html", ".j2", ".comp", ".ini", ".hal",
                 ".sh", ".md", ".toml"}
CITE_SKIP = {".venv", ".peers", ".git", "build", "node_modules", "__pycache__"}
CITE_ALLOWED = {"docs/README-MIGRATION.md", "docs/gen/text.py", "tests/test_architecture.py"}


def issue_cites(root: Path) -> list[str]:
    found = []
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root)
        if (not p.is_file() or (p.suffix not in CITE_SUFFIXES and p.name != "Makefile")
                or CITE_SKIP & set(rel.parts) or rel.as_posix() in CITE_ALLOWED):
            continue
        for n, line in enumerate(p.read_text(errors="replace").splitlines(), 1):
            if ISSUE_CITE.search(line):
                found.append(f"{rel}:{n}: {line.strip()[:100]}")
    return found


def test_no_issue_number_in_code_config_or_docs():
    assert issue_cites(ROOT) == []


def test_an_issue_number_in_a_comment_is_caught(tmp_path):
    (tmp_path / "m.py").write_text("x = 1  # the drift (issue 22)\n# LinuxCNC #3650\n")
    (tmp_path / "c.yaml").write_text("# swivel head, issue-24 plan\n")
    assert [c.split(":")[0] for c in issue_cites(tmp_path)] == ["c.yaml", "m.py"]


# SQL lives in daemon/store/ only: every other module asks the store a question by name. A
# statement is recognised by its shape (keyword followed by what must follow it), uppercase as
# the project writes SQL, in any string literal that is not a docstring (f-strings with their
# holes as "?"), so "Select" (a SINUMERIK method) or "RESELECT THE CARRIER" do not count.
SQL = re.compile(r"\bSELECT\b[\s\S]+?\bFROM\b|\bINSERT\s+(?:OR\s+\w+\s+)?INTO\b"
                 r"|\bUPDATE\s+\S+\s+SET\b|\bDELETE\s+FROM\b"
                 r"|\bCREATE\s+(?:UNIQUE\s+)?(?:TABLE|INDEX|VIEW)\b|\b(?:ALTER|DROP)\s+TABLE\b")
SQL_HOME = "daemon/store/"


def _literals(tree: ast.AST) -> list[tuple[int, str]]:
    docs = {id(n.body[0].value) for n in ast.walk(tree)
            if isinstance(n, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
            and n.body and isinstance(n.body[0], ast.Expr)
            and isinstance(n.body[0].value, ast.Constant)}
    out = []
    for n in ast.walk(tree):
        if isinstance(n, ast.Constant) and isinstance(n.value, str) and id(n) not in docs:
            out.append((n.lineno, n.value))
        elif isinstance(n, ast.JoinedStr):
            out.append((n.lineno, "".join(v.value if isinstance(v, ast.Constant) else "?"
                                          for v in n.values)))
    return out


def sql_outside_store(root: Path) -> list[str]:
    found = []
    for pkg in OURS:
        for p in sorted((root / pkg).rglob("*.py")):
            rel = p.relative_to(root).as_posix()
            if rel.startswith(SQL_HOME):
                continue
            for line, text in _literals(ast.parse(p.read_text(encoding="utf-8"), rel)):
                if SQL.search(text):
                    found.append(f"{rel}:{line}: {' '.join(text.split())[:80]}")
    return sorted(found)


def test_sql_only_in_the_store():
    assert sql_outside_store(ROOT) == []


def test_sql_outside_the_store_is_caught(tmp_path):
    (tmp_path / "daemon" / "hmi").mkdir(parents=True)
    (tmp_path / "daemon" / "store").mkdir()
    for pkg in set(OURS) - {"daemon"}:
        (tmp_path / pkg).mkdir()
    (tmp_path / "daemon" / "hmi" / "v.py").write_text(
        '"""SELECT the run FROM the list (prose)."""\n'
        'SELECT = "Select"\nNOTE = "RESELECT THE CARRIER FROM THE MAGAZINE"\n'
        'q = f"SELECT {cols} FROM runs WHERE id=?"\n'
        'w = ("UPDATE compensations"\n     " SET state=?")\n')
    (tmp_path / "daemon" / "store" / "s.py").write_text('q = "DELETE FROM runs"\n')
    (tmp_path / "benchmarks" / "b.py").write_text('c.execute("INSERT INTO m VALUES (%s)")\n')
    assert [f.rsplit(":", 1)[0] for f in sql_outside_store(tmp_path)] == [
        "benchmarks/b.py:1", "daemon/hmi/v.py:4", "daemon/hmi/v.py:5"]


# The tests stand on the product, never the other way: no package of ours (benchmarks and demos
# included) imports ``tests``. What both need (the replay link, exact synthetic logs, the rigs
# of simulated CNCs) lives in the product or in benchmarks/rigs/. One named exception: the
# fuzz campaign runs the input property tests themselves with larger budgets.
TESTS_IMPORT_ALLOWED = {"benchmarks.fuzz.inputs"}


def _imports_tests(path: Path) -> bool:
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import) and any(a.name.split(".")[0] == "tests"
                                                for a in node.names):
            return True
        if (isinstance(node, ast.ImportFrom) and node.level == 0 and node.module
                and node.module.split(".")[0] == "tests"):
            return True
    return False


def test_nothing_of_ours_imports_the_tests():
    files = [p for pkg in OURS for p in (ROOT / pkg).rglob("*.py")]
    assert sorted(_module(p) for p in files if _imports_tests(p)) == sorted(TESTS_IMPORT_ALLOWED)


def test_an_import_of_the_tests_is_caught(tmp_path):
    cases = {"a.py": "def f():\n    from tests.synth import make_rows\n",
             "b.py": "import tests.test_e2e_transports as e2e\n",
             "c.py": "from tests import replay_link\n",
             "d.py": "from benchmarks.rigs import rig_helpers\nimport testsuite\n"}
    for name, text in cases.items():
        (tmp_path / name).write_text(text)
    assert [n for n in cases if _imports_tests(tmp_path / n)] == ["a.py", "b.py", "c.py"]


# A configuration is read and checked without the runtime: the schemas and loaders (daemon/
# config.py, daemon/*/config.py, drivers/*/schema.py) reach, through any chain of our imports,
# no protocol stack, web server or renderer. `rumba check` stays light, and a schema cannot
# come to depend on the HMI's or a link's state.
RUNTIME_LIBS = {"aiohttp", "asyncua", "pymodbus", "serial", "serial_asyncio", "can", "psycopg",
                "aiomqtt", "matplotlib", "jinja2", "pylsv2", "linuxcnc"}
PARSERS = {"psycopg.conninfo"}  # libpq's own URL parser checks store.url, nothing connects


def _config_modules(graph: dict[str, set[str]]) -> list[str]:
    return sorted(m for m in graph if m == "daemon.config" or (
        m.split(".")[0] in ("daemon", "drivers") and m.rsplit(".", 1)[-1] in ("config", "schema")
        and m != "daemon.store.schema"))  # the journal's migrations, not a configuration


def _reach(graph: dict[str, set[str]], start: str) -> set[str]:
    seen, todo = {start}, [start]
    while todo:
        for dep in graph[todo.pop()] - seen:
            seen.add(dep)
            todo.append(dep)
    return seen


def _runtime_libraries(module: str) -> set[str]:
    """The runtime libraries ``module`` imports, at any depth of the file."""
    path = ROOT / (module.replace(".", "/") + ".py")
    if not path.exists():
        path = ROOT / module.replace(".", "/") / "__init__.py"
    names = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.update(f"{node.module}.{a.name}" for a in node.names)
    return {n.split(".")[0] for n in names
            if n.split(".")[0] in RUNTIME_LIBS and not any(n.startswith(p) for p in PARSERS)}


def runtime_in_configuration(graph: dict[str, set[str]]) -> list[str]:
    return sorted(f"{c} reaches {m} ({', '.join(sorted(_runtime_libraries(m)))})"
                  for c in _config_modules(graph) for m in sorted(_reach(graph, c))
                  if _runtime_libraries(m))


def test_configuration_schemas_import_no_runtime():
    assert len(_config_modules(GRAPH)) >= 10  # the walker sees them
    assert runtime_in_configuration(GRAPH) == []


def test_a_runtime_import_in_a_schema_is_caught():
    graph = {m: set(deps) for m, deps in GRAPH.items()}
    graph["daemon.config"].add("daemon.hmi.limits")  # the HMI's request limits: aiohttp
    assert runtime_in_configuration(graph) == ["daemon.config reaches daemon.hmi.limits (aiohttp)"]
