"""The manual (docs/): its reference pages are what the code generates now, the site builds
with every warning an error (links, anchors, includes), every shell example is run or says why
not, the README's links reach the manual, and no page names the project's issues."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.docs_examples import DOCS, KINDS, ROOT, blocks, make_recipe, pages, run_page

SHELL = ("sh", "bash", "shell", "console")
READMES = [ROOT / "README.md", DOCS / "README.next.md"]


def test_reference_pages_are_what_the_code_generates_now():
    from docs.gen.__main__ import main

    assert main(["--check"]) == 0, "run `make docs` and commit docs/reference/"


def test_the_generator_sees_a_change_of_the_code(monkeypatch):
    """A new option, key or register must change a page (else the check above proves nothing)."""
    from contracts import modbus_map
    from docs.gen import maps
    from docs.gen.__main__ import generate

    before = generate()["modbus-map.md"]
    reg = modbus_map.Reg("SPARE", 17, 1, "u16", "cnc", "a register added to the map")
    monkeypatch.setattr(modbus_map, "REGISTERS", (*modbus_map.REGISTERS, reg))
    assert maps.modbus() != before and "`SPARE`" in maps.modbus()


def test_site_builds_with_warnings_as_errors(tmp_path):
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}  # the theme's banner about its successor
    p = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir",
                        str(tmp_path / "site")], cwd=ROOT, env=env, capture_output=True, text=True,
                       timeout=600)
    assert p.returncode == 0, p.stderr[-4000:]
    assert (tmp_path / "site/index.html").is_file()
    assert (tmp_path / "site/tutorials/first-check.html").is_file()


def test_every_shell_example_is_run_or_says_why_not():
    problems = []
    for path in [*pages(), DOCS / "README.next.md"]:
        if not path.exists():
            continue
        for b in blocks(path):
            if b.lang in SHELL:
                if b.kind not in KINDS or b.kind == "stdin":
                    problems.append(f"{b.where}: no doctest marker (one of {KINDS[:-1]})")
                elif b.kind == "skip" and len(b.options.get("reason", "")) < 10:
                    problems.append(f"{b.where}: skip without a reason")
                elif b.kind == "covered-by":
                    problems += _covered(b)
            elif b.kind == "stdin" and "name" not in b.options:
                problems.append(f"{b.where}: stdin without the background process's name")
    assert problems == []


def _covered(b) -> list[str]:
    runs, test = b.options.get("runs", ""), ROOT / b.target
    if not runs or not test.is_file():
        return [f"{b.where}: covered-by needs an existing test file and runs=MODULE"]
    out = []
    if runs not in test.read_text(encoding="utf-8"):
        out.append(f"{b.where}: {b.target} does not run {runs}")
    for target in re.findall(r"\bmake ([\w-]+)", b.body):
        if runs not in make_recipe(target):
            out.append(f"{b.where}: make {target} does not run {runs}")
    return out


def test_no_page_names_the_projects_issues():
    found = [f"{p.relative_to(ROOT)}:{n}: {line.strip()}"
             for p in [*pages(), DOCS / "README.next.md"] if p.exists()
             for n, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1)
             if re.search(r"\bissues? \d+", line, re.I)]
    assert found == []


@pytest.mark.parametrize("readme", READMES, ids=lambda p: p.name)
def test_the_readme_links_resolve(readme):
    """Relative links and images of a README reach a file (a manual page, a picture)."""
    if not readme.exists():
        pytest.skip(f"{readme.name} not written")
    text = readme.read_text(encoding="utf-8")
    links = re.findall(r"\]\(([^)\s]+)\)", text) + re.findall(r'src="([^"]+)"', text)
    local = [link.split("#")[0] for link in links if not re.match(r"[a-z]+:", link)]
    # README.next.md is written for the repository's root, where it will replace README.md
    missing = [link for link in local if link and not (ROOT / link).exists()]
    assert missing == []
    if readme.name == "README.next.md":  # it lives in docs/ until it is swapped in: from root
        assert any(link.endswith("docs/tutorials/first-check.md") for link in local)


def _runnable(path: Path) -> bool:
    return any(b.kind in ("run", "background") for b in blocks(path))


def _marks(path: Path):
    marks = [pytest.mark.slow] if any(b.kind == "background" for b in blocks(path)) else []
    if "linuxcnc" in path.name:
        marks.append(pytest.mark.linuxcnc)
    return marks


@pytest.mark.parametrize("page", [pytest.param(p, marks=_marks(p), id=str(p.relative_to(DOCS)))
                                  for p in pages() if _runnable(p)])
def test_the_pages_examples_run(page, tmp_path):
    assert run_page(page, tmp_path) > 0
