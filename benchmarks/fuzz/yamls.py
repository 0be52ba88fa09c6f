"""Target 2: every YAML schema loader on mutations of the shipped configuration files."""

from __future__ import annotations

import math
import random
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml

from benchmarks.fuzz.common import CONFIG, Tally, rand_text, run_case, short

UNKNOWN = "zz_unknown_key"


def loaders(tmp: Path) -> list[tuple[str, Path, Callable[[Path], object]]]:
    """(kind, shipped file, loader) for every schema; daemon.yaml is the tests' own layout."""
    from benchmarks.rigs.daemon_helpers import write_daemon_yaml
    from contracts.setup_files import load_artefact, load_machine, load_plan
    from daemon.config import load_daemon_config
    from simulators.errors_schema import load_errors
    from simulators.faults import FaultPlan

    out: list[tuple[str, Path, Callable[[Path], object]]] = []
    for kind, sub, fn in (("machine", "machines", load_machine),
                          ("artefact", "artefacts", load_artefact),
                          ("plan", "plans", load_plan), ("errors", "errors", load_errors),
                          ("faults", "faults", FaultPlan.load)):
        out += [(kind, p, fn) for p in sorted((CONFIG / sub).glob("*.yaml"))]
    base = tmp / "base"
    base.mkdir()
    out.append(("daemon", write_daemon_yaml(base), load_daemon_config))
    return out


def _paths(node: Any, at: tuple = ()) -> list[tuple]:
    out = [at]
    if isinstance(node, dict):
        for k, v in node.items():
            out += _paths(v, (*at, k))
    elif isinstance(node, list):
        for k, v in enumerate(node):
            out += _paths(v, (*at, k))
    return out


def _get(node: Any, at: tuple) -> Any:
    for k in at:
        node = node[k]
    return node


def rand_scalar(rng: random.Random) -> Any:
    return rng.choice([
        float("nan"), float("inf"), -float("inf"), 1e308, -1e308, 1e-320, 0, -1, 10**30,
        True, None, "", " ", "٣", "１", "1_0", "nan", rand_text(rng), [], {}, [1, 2],
        {UNKNOWN: 1}, rng.uniform(-1e6, 1e6), rng.randint(-10**6, 10**6), "../../etc/passwd",
        "x" * 5000])


def mutate(rng: random.Random, text: str) -> tuple[bytes, list[str], set[str]]:
    """Mutated document, operations applied, and planted faults the loader must refuse."""
    planted: set[str] = set()
    r = rng.random()
    if r < 0.05:
        depth = rng.choice((1000, 50_000))
        return (("a: " + "[" * depth + "]" * depth + "\n").encode(), [f"nesting {depth}"],
                {"invalid"})
    if r < 0.10:
        digits = rng.choice((4400, 5000, 50_000))
        return (text + f"\n{UNKNOWN}: {'9' * digits}\n").encode(), [f"{digits}-digit int"], \
            {"unknown"}
    if r < 0.15:
        data = text.encode()
        at = rng.randrange(len(data))
        return (data[:at] + b"\xff\xfe" + data[at:], [f"non-UTF-8 at {at}"],
                {"invalid"})
    if r < 0.18:
        return (b"\xef\xbb\xbf" + text.encode(), ["UTF-8 BOM"], set())
    if r < 0.22:
        return rand_text(rng, 80).encode("utf-8", "surrogatepass"), ["random text"], set()
    doc = yaml.safe_load(text)
    ops: list[str] = []
    for _ in range(rng.choice((1, 1, 2, 3))):
        paths = _paths(doc)
        at = rng.choice(paths)
        node = _get(doc, at)
        op = rng.random()
        if op < 0.25 and isinstance(node, dict):
            node[rng.choice((UNKNOWN, UNKNOWN.upper(), "Name", "nme"))] = rand_scalar(rng)
            planted.add("unknown")
            ops.append(f"{'.'.join(map(str, at)) or '<top>'}: unknown key added")
        elif op < 0.35 and isinstance(node, dict) and node:
            k = rng.choice(list(node))
            del node[k]
            ops.append(f"{'.'.join(map(str, (*at, k)))}: deleted")
        elif op < 0.45 and "step_deg" in str(at):
            parent = _get(doc, at[:-1])
            parent[at[-1]] = rng.choice((1e-7, 1e-4, 0.0, -1.0))
            ops.append(f"{'.'.join(map(str, at))} := {parent[at[-1]]!r}")
        elif at:
            parent = _get(doc, at[:-1])
            value = rand_scalar(rng)
            parent[at[-1]] = value
            ops.append(f"{'.'.join(map(str, at))} := {short(value, 60)}")
    if rng.random() < 0.1 and isinstance(doc, dict) and "grid" in doc:
        doc["grid"] = {"b": {"start_deg": -90, "stop_deg": 90, "step_deg": 1e-7},
                       "c": {"start_deg": 0, "stop_deg": 360, "step_deg": 1e-7}}
        ops.append("grid step_deg 1e-7")
    return yaml.safe_dump(doc, allow_unicode=True).encode(), ops, planted


def _has_planted_key(node: Any) -> bool:
    if isinstance(node, dict):
        return (any(k in (UNKNOWN, UNKNOWN.upper(), "Name", "nme") for k in node)
                or any(_has_planted_key(v) for v in node.values()))
    if isinstance(node, list):
        return any(_has_planted_key(v) for v in node)
    return False


def _nonfinite(node: Any) -> bool:
    if isinstance(node, float):
        return not math.isfinite(node)
    if isinstance(node, dict):
        return any(_nonfinite(v) for v in node.values())
    if isinstance(node, list):
        return any(_nonfinite(v) for v in node)
    return False


def fuzz(rng: random.Random, n: int, limit_s: float = 5.0) -> Tally:
    from contracts.yaml_files import ConfigError

    tally = Tally("YAML loaders")
    with tempfile.TemporaryDirectory(prefix="rumba-fuzz-") as tmp_s:
        tmp = Path(tmp_s)
        targets = loaders(tmp)
        for i in range(n):
            kind, src, load = targets[i % len(targets)]
            text = src.read_text(encoding="utf-8")
            data, ops, planted = mutate(rng, text)
            path = tmp / f"fuzz-{kind}-{i}.yaml"

            def case(kind: str = kind, load: Callable[[Path], object] = load,
                     data: bytes = data, planted: set[str] = planted,
                     path: Path = path) -> tuple[str, str]:
                path.write_bytes(data)
                try:
                    try:
                        load(path)
                    except ConfigError as e:
                        if path.name not in str(e):
                            return "traceback", f"ConfigError without the file name: {e}"
                        return "clean", str(e)[:200]
                    try:
                        parsed = yaml.safe_load(data.decode("utf-8"))
                    except (yaml.YAMLError, UnicodeDecodeError, ValueError, RecursionError):
                        parsed = None
                    if "unknown" in planted and _has_planted_key(parsed):
                        return "wrong", f"{kind}: accepted with an unknown key"
                    if _nonfinite(parsed):
                        return "wrong", f"{kind}: accepted with a non-finite number"
                    return "accepted", ""
                finally:
                    path.unlink(missing_ok=True)

            run_case(tally, limit_s, case,
                     lambda i=i, kind=kind, src=src, ops=ops:
                     f"case {i} {kind} {src.name}: {'; '.join(ops)}")
    return tally
