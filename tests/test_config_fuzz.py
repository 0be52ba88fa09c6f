"""YAML robustness of every file schema (machine, artefact, plan, daemon.yaml, errors, faults):
hostile files (not UTF-8, deep nesting, huge integers, non-finite numbers, oversize files,
alias bombs, huge grids) and random mutations of the shipped files either load or end as one
``ConfigError`` line naming the file — never another exception, never an unknown key accepted."""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from contracts.setup_files import MAX_POSES, MAX_TOUCHES, load_artefact, load_machine, load_plan
from contracts.yaml_files import MAX_YAML_BYTES, ConfigError, read_yaml
from daemon.config import load_daemon_config
from simulators.errors_schema import load_errors
from simulators.faults import FaultPlan

CONFIG = Path(__file__).resolve().parent.parent / "config"


def _daemon_doc(tmp: Path) -> dict:
    """A daemon.yaml that loads on this machine (shipped files by absolute path, serial link)."""
    return {"store": {"path": str(tmp / "j.sqlite")}, "reports_dir": str(tmp / "reports"),
            "hmi": {"token": "t" * 16},
            "machines": [{"name": "m1", "machine": str(CONFIG / "machines/thesis_wcbxfzyt.yaml"),
                          "artefact": str(CONFIG / "artefacts/thesis_4ball.yaml"),
                          "plan": str(CONFIG / "plans/thesis_ch3_7poses.yaml"),
                          "dialect": "fanuc",
                          "link": {"transport": "serial", "url": "/dev/ttyS0",
                                   "request_machine": "m1"},
                          "tolerances": {"links": {"EB0Z": {"warn": 20, "fail": 40}},
                                         "residual_rms_um": 5}}]}


def _shipped(rel: str) -> Callable[[Path], dict]:
    return lambda _tmp: yaml.safe_load((CONFIG / rel).read_text(encoding="utf-8"))


# schema → (loader, base document, mappings whose keys are free (not schema keys))
SCHEMAS: dict[str, tuple[Callable[[Path], Any], Callable[[Path], dict], set[str]]] = {
    "machine": (load_machine, _shipped("machines/thesis_wcbxfzyt.yaml"), set()),
    "machine-lcnc": (load_machine, _shipped("machines/linuxcnc_xyzbc.yaml"), set()),
    "artefact": (load_artefact, _shipped("artefacts/thesis_4ball_scaled.yaml"), set()),
    "plan": (load_plan, _shipped("plans/shift_start_14poses.yaml"), set()),
    "plan-grid": (load_plan, _shipped("plans/thesis_ch4_175poses.yaml"), set()),
    "daemon": (load_daemon_config, _daemon_doc, set()),
    "errors": (load_errors, _shipped("errors/thesis_effects_demo.yaml"),
               {"setup.balls_um", "effects.*.params", "effects.*.options"}),
    "faults": (FaultPlan.load, _shipped("faults/dnc_trouble.yaml"), set()),
}


def _load(schema: str, tmp: Path, text: str | bytes) -> Any:
    path = tmp / f"{schema}.yaml"
    path.write_bytes(text if isinstance(text, bytes) else text.encode("utf-8"))
    return path, SCHEMAS[schema][0](path)


def _refused(schema: str, tmp: Path, text: str | bytes, *needles: str) -> str:
    path = tmp / f"{schema}.yaml"
    with pytest.raises(ConfigError) as info:
        _load(schema, tmp, text)
    msg = str(info.value)
    assert msg.startswith(f"{path}:") and len(msg.splitlines()) == 1, msg
    for n in needles:
        assert n in msg, msg
    return msg


# ------------------------------------------------------------------- hostile files


@pytest.mark.parametrize("schema", sorted(SCHEMAS))
def test_hostile_files_are_one_config_error(schema, tmp_path):
    _refused(schema, tmp_path, b"name: \xff\xfe caf\xe9\n", "not UTF-8")
    _refused(schema, tmp_path, "a: " + "[" * 50_000 + "]" * 50_000 + "\n", "nested")
    _refused(schema, tmp_path, "a: " + "1" * 5000 + "\n")  # int conversion limit
    _refused(schema, tmp_path, "a: " + "[" * 40 + "1" + "]" * 40 + "\n", "nested deeper")
    _refused(schema, tmp_path, "# " + "x" * MAX_YAML_BYTES + "\n", "larger than")
    bomb = "a: &a [1,1,1,1,1,1,1,1,1,1]\n" + "".join(
        f"{c}: &{c} [*{p},*{p},*{p},*{p},*{p},*{p},*{p},*{p},*{p},*{p}]\n"
        for p, c in zip("abcdefgh", "bcdefghi", strict=True))
    _refused(schema, tmp_path, bomb, "values")
    _refused(schema, tmp_path, "a: [1\n", "not valid YAML")


def test_missing_file_and_nul_in_path(tmp_path):
    with pytest.raises(ConfigError, match="cannot read"):
        read_yaml(tmp_path / "none.yaml")
    with pytest.raises(ConfigError, match="cannot read"):
        read_yaml(tmp_path / "a\x00b.yaml")


NONFINITE = [".nan", ".inf", "-.inf", "1.0e400", "'nan'", "'1e400'", "-1.0e400"]
# (schema, dotted key, YAML text with {v})
NONFINITE_SITES = [
    ("plan", "poses.0.b_deg", "name: p\nstylus_diameter_mm: 6\nposes: [{{b_deg: {v}, c_deg: 0}}]"),
    ("plan", "poses.0.c_deg", "name: p\nstylus_diameter_mm: 6\nposes: [[0, {v}]]"),
    ("plan", "grid.b.start_deg", "name: p\nstylus_diameter_mm: 6\ngrid: {{b: {{start_deg: {v}, "
     "stop_deg: 45, step_deg: 15}}, c: {{start_deg: 0, stop_deg: 90, step_deg: 15}}}}"),
    ("plan", "grid.c.stop_deg", "name: p\nstylus_diameter_mm: 6\ngrid: {{b: {{start_deg: 0, "
     "stop_deg: 45, step_deg: 15}}, c: {{start_deg: 0, stop_deg: {v}, step_deg: 15}}}}"),
    ("plan", "grid.c.step_deg", "name: p\nstylus_diameter_mm: 6\ngrid: {{b: {{start_deg: 0, "
     "stop_deg: 45, step_deg: 15}}, c: {{start_deg: 0, stop_deg: 90, step_deg: {v}}}}}"),
]


def _machine_text(**over: str) -> str:
    data = yaml.safe_load((CONFIG / "machines/thesis_wcbxfzyt.yaml").read_text())
    text = yaml.safe_dump(data)
    for key, v in over.items():
        head, _, tail = key.partition(".")
        data2 = copy.deepcopy(data)
        data2.setdefault(head, {})[tail] = "@@"
        text = yaml.safe_dump(data2).replace("'@@'", v)
    return text


@pytest.mark.parametrize("v", NONFINITE)
def test_non_finite_numbers_are_refused_naming_the_key(v, tmp_path):
    for schema, key, text in NONFINITE_SITES:
        _refused(schema, tmp_path, text.format(v=v), key)
    for key, val in [("table.surface_z_mm", v), ("tool.tip_mm", f"[0, 0, {v}]"),
                     ("tool.spindle_axis", f"[{v}, 0, 1]"), ("dynamics.rapid_mm_min", v)]:
        _refused("machine", tmp_path, _machine_text(**{key: val}), key)
    art = yaml.safe_load((CONFIG / "artefacts/thesis_4ball.yaml").read_text())
    art["balls"][0]["position_mm"] = "@@"
    _refused("artefact", tmp_path, yaml.safe_dump(art).replace("'@@'", f"[0, {v}, 1]"),
             "balls.0.position_mm")
    _refused("errors", tmp_path, f"links: {{EB0Z: {v}}}", "links.EB0Z")
    _refused("errors", tmp_path, f"effects: [{{family: x, params: {{a: {v}}}}}]",
             "effects.0.params.a")
    _refused("faults", tmp_path, f"faults: [{{kind: alarm, at_time_s: {v}}}]",
             "faults.0.at_time_s")


@pytest.mark.parametrize("v", ["1.0e308", "-1.0e30", "100000.1"])
def test_absurd_but_finite_lengths_are_refused_naming_the_key(v, tmp_path):
    """Found by the fuzz campaign: 1e308 in a rotary point or a ball position reached the
    kinematics and ended as an internal 'singular matrix' error instead of naming the key."""
    data = yaml.safe_load((CONFIG / "machines/thesis_wcbxfzyt.yaml").read_text())
    axis = next(k for k, a in data["axes"].items() if "point_mm" in a)
    data["axes"][axis]["point_mm"] = "@@"
    _refused("machine", tmp_path, yaml.safe_dump(data).replace("'@@'", f"[0, {v}, 0]"),
             f"axes.{axis}.point_mm.1", "100000")
    art = yaml.safe_load((CONFIG / "artefacts/thesis_4ball.yaml").read_text())
    art["balls"][1]["position_mm"] = "@@"
    _refused("artefact", tmp_path, yaml.safe_dump(art).replace("'@@'", f"[{v}, 0, 1]"),
             "balls.1.position_mm.0", "100000")


def test_link_sections_refuse_non_finite_timeouts(tmp_path):
    doc = _daemon_doc(tmp_path)
    doc["machines"][0]["link"]["xoff_timeout_s"] = float("inf")
    _refused("daemon", tmp_path, yaml.safe_dump(doc), "xoff_timeout_s")


def test_a_link_name_with_a_trailing_newline_is_refused():
    from simulators.errors_schema import errors_from_dict

    with pytest.raises(ConfigError, match="links"):
        errors_from_dict({"links": {"EB0Z\n": 1.0}}, "e.yaml")


# ------------------------------------------------------------------- resource ceilings


def test_a_tiny_grid_step_is_refused_at_once_naming_file_and_key(tmp_path):
    # counted from range / step before anything is expanded (the expansion ran out of memory)
    _refused("plan", tmp_path, "name: p\nstylus_diameter_mm: 6\ngrid: {b: {start_deg: -45, "
             "stop_deg: 45, step_deg: 1.0e-7}, c: {start_deg: 0, stop_deg: 360, "
             "step_deg: 15}}\n", "grid:", f"ceiling of {MAX_POSES}")
    _refused("plan", tmp_path, "name: p\nstylus_diameter_mm: 6\ngrid: {b: {start_deg: -9.0e4, "
             "stop_deg: 9.0e4, step_deg: 1.0e-300}, c: {start_deg: 0, stop_deg: 1, "
             "step_deg: 1}}\n", "grid:")
    _refused("plan", tmp_path, "name: p\nstylus_diameter_mm: 6\ngrid: {b: {start_deg: -1.0e308, "
             "stop_deg: 1.0e308, step_deg: 1}, c: {start_deg: 0, stop_deg: 1, "
             "step_deg: 1}}\n", "grid.b.start_deg:", "greater than or equal to -100000")


def test_pose_list_ceiling(tmp_path):
    poses = "[" + ", ".join(["[0, 0]"] * (MAX_POSES + 1)) + "]"
    _refused("plan", tmp_path, f"name: p\nstylus_diameter_mm: 6\nposes: {poses}\n", "poses:",
             f"ceiling of {MAX_POSES}")
    ok = "[" + ", ".join(["[0, 0]"] * MAX_POSES) + "]"
    _, plan = _load("plan", tmp_path, f"name: p\nstylus_diameter_mm: 6\nposes: {ok}\n")
    assert len(plan.poses) == MAX_POSES


def test_touch_ceiling_in_daemon_yaml_and_rumba_gcode(tmp_path, capsys):
    from daemon.cli.main import main

    grid = ("name: big\nstylus_diameter_mm: 6\nrepeats: 20\ngrid: {b: {start_deg: -45, "
            "stop_deg: 45, step_deg: 15}, c: {start_deg: 0, stop_deg: 360, step_deg: 15}}\n")
    plan = tmp_path / "big.yaml"
    plan.write_text(grid)  # 175 poses × 20 repeats × 4 balls × 5 = 70 000 touches
    doc = _daemon_doc(tmp_path)
    doc["machines"][0]["plan"] = str(plan)
    doc["machines"][0]["tolerances"] = {}
    _refused("daemon", tmp_path, yaml.safe_dump(doc), "machines.0.plan:",
             f"ceiling of {MAX_TOUCHES}")
    argv = ["gcode", "--machine", str(CONFIG / "machines/thesis_wcbxfzyt.yaml"), "--artefact",
            str(CONFIG / "artefacts/thesis_4ball.yaml"), "--plan", str(plan), "--dialect",
            "fanuc"]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"error: {plan}: poses: 70000 touches"), err


# ------------------------------------------------------------------- property: mutations


def _paths(node: Any, prefix: tuple = ()) -> list[tuple]:
    out = [prefix]
    if isinstance(node, dict):
        for k, v in node.items():
            out += _paths(v, (*prefix, k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out += _paths(v, (*prefix, i))
    return out


def _get(node: Any, path: tuple) -> Any:
    for k in path:
        node = node[k]
    return node


def _free(path: tuple, free: set[str]) -> bool:
    dotted = ".".join("*" if isinstance(k, int) else str(k) for k in path)
    return dotted in free or any(dotted.startswith(f + ".") for f in free)


SCALARS = st.one_of(
    st.none(), st.booleans(), st.integers(), st.integers(-10**30, 10**30).map(lambda x: x**3),
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=30),
    st.sampled_from(["", "\n", "abc\n", "(M30)", "1e400", "nan", "0x10", "-0", "yes", "~"]))
VALUES = st.recursive(SCALARS, lambda kids: st.one_of(
    st.lists(kids, max_size=4), st.dictionaries(st.text(max_size=8), kids, max_size=3)),
    max_leaves=8)


@st.composite
def mutations(draw: st.DrawFn, base: dict) -> tuple[dict, tuple | None]:
    """Up to three mutations; returns the document and the path of an added unknown key."""
    doc = copy.deepcopy(base)
    unknown = None
    for _ in range(draw(st.integers(1, 3))):
        paths = _paths(doc)
        path = draw(st.sampled_from(paths))
        op = draw(st.sampled_from(["replace", "replace", "delete", "unknown", "deep"]))
        parent = _get(doc, path[:-1]) if path else None
        if op == "replace" and path:
            parent[path[-1]] = draw(VALUES)
        elif op == "deep" and path:
            v: Any = draw(SCALARS)
            for _ in range(draw(st.integers(1, 40))):
                v = [v]
            parent[path[-1]] = v
        elif op == "delete" and path and isinstance(parent, dict):
            del parent[path[-1]]
        elif op == "unknown":
            node = _get(doc, path)
            if isinstance(node, dict):
                node["zz_fuzz_unknown"] = draw(SCALARS)
                unknown = path
    return doc, unknown


def _dump(doc: Any) -> str | None:
    try:
        return yaml.safe_dump(doc, allow_unicode=False)
    except (yaml.YAMLError, RecursionError):
        return None


@pytest.mark.parametrize("schema", sorted(SCHEMAS))
def test_random_mutations_load_or_are_one_config_error(schema, tmp_path_factory):
    tmp = tmp_path_factory.mktemp(schema)
    loader, base_of, free = SCHEMAS[schema]
    base = base_of(tmp)
    _load(schema, tmp, yaml.safe_dump(base))  # the unmutated document loads

    @settings(max_examples=25, deadline=None, database=None,
              suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
    @given(mutations(base))
    def check(mut: tuple[dict, tuple | None]) -> None:
        doc, unknown = mut
        text = _dump(doc)
        if text is None:
            return
        path = tmp / f"{schema}.yaml"
        path.write_text(text, encoding="utf-8")
        try:
            loader(path)
        except ConfigError as e:
            msg = str(e)
            assert msg.startswith(f"{path}:") and len(msg.splitlines()) == 1, msg
            assert msg.isprintable(), msg
            return
        assert unknown is None or _free(unknown, free) or not _still_there(path, unknown), \
            f"unknown key at {unknown} accepted"

    check()


def _still_there(path: Path, where: tuple) -> bool:
    """Whether the unknown key survived later mutations (a parent may have been replaced)."""
    try:
        node = _get(yaml.safe_load(path.read_text()), where)
    except (KeyError, IndexError, TypeError):
        return False
    return isinstance(node, dict) and "zz_fuzz_unknown" in node


def test_shipped_files_all_load():
    for p in sorted((CONFIG / "machines").glob("*.yaml")):
        load_machine(p)
    for p in sorted((CONFIG / "artefacts").glob("*.yaml")):
        load_artefact(p)
    for p in sorted((CONFIG / "plans").glob("*.yaml")):
        plan = load_plan(p)
        assert all(math.isfinite(x.b_deg) for x in plan.poses)
    for p in sorted((CONFIG / "errors").glob("*.yaml")):
        load_errors(p)
    for p in sorted((CONFIG / "faults").glob("*.yaml")):
        FaultPlan.load(p)
