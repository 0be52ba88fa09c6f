"""`rumba gap selfcheck` finds its machine, artefact and plan in the installed package, not in a
checkout's config/ folder; the shipped copies stay identical to config/."""

from __future__ import annotations

import ast
import subprocess
import sys
from importlib import resources
from pathlib import Path

import pytest

from daemon.cli.commands import gap

ROOT = Path(__file__).resolve().parents[1]
SOURCES = {"thesis_wcbxfzyt.yaml": "machines", "thesis_4ball.yaml": "artefacts",
           "thesis_annexB_14poses.yaml": "plans"}


def test_every_default_is_package_data_identical_to_config():
    assert set(gap.DEFAULTS) == set(SOURCES)
    for name, folder in SOURCES.items():
        shipped = resources.files("daemon.cli").joinpath("defaults", name)
        assert shipped.is_file()
        assert shipped.read_bytes() == (ROOT / "config" / folder / name).read_bytes(), name
        assert gap.default_file(name) == Path(str(shipped))


def test_an_unknown_default_is_refused():
    with pytest.raises(ValueError, match="not a shipped default"):
        gap.default_file("../../config/daemon.yaml")


def test_no_daemon_module_looks_for_files_beside_its_source():
    users = [str(p.relative_to(ROOT)) for p in (ROOT / "daemon").rglob("*.py")
             if any(isinstance(n, ast.Name) and n.id == "__file__"
                    for n in ast.walk(ast.parse(p.read_text(encoding="utf-8"))))]
    assert users == []


def test_pyproject_ships_the_defaults():
    text = (ROOT / "pyproject.toml").read_text(encoding="utf-8")
    assert '"daemon.cli" = ["defaults/*.yaml"]' in text


def test_the_defaults_load_away_from_the_checkout(tmp_path):
    # another working directory: a relative lookup of config/ would miss
    code = ("from contracts.setup_files import load_artefact, load_machine, load_plan\n"
            "from daemon.cli.commands.gap import default_file as f\n"
            "m, _ = load_machine(f('thesis_wcbxfzyt.yaml'))\n"
            "a = load_artefact(f('thesis_4ball.yaml'))\n"
            "p = load_plan(f('thesis_annexB_14poses.yaml'))\n"
            "print(m.name, a.name, len(p.poses))")
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split()[-1] == "14"
