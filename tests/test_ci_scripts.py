"""The CI shell scripts run under pipefail: no pipe may end in a reader that quits early."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# A reader that stops before end of input makes the writer die of SIGPIPE; under
# `set -o pipefail` that is exit 141 for the whole script, depending on timing (the CI failure
# of 2026-11-22 came from `pdftoppm -v | head -n1`).
EARLY_QUIT = re.compile(
    r"\|\s*(head\b|grep\s+-[a-zA-Z]*[qm]|awk\s+'[^']*\bexit\b|sed\s+[^|]*\bq\b)"
)


def _pipefail_scripts() -> list[Path]:
    scripts = sorted((ROOT / ".ci").glob("*")) + sorted((ROOT / "scripts").glob("*.sh"))
    return [p for p in scripts if p.is_file() and "pipefail" in p.read_text(errors="replace")]


def test_ci_scripts_are_found() -> None:
    names = {p.name for p in _pipefail_scripts()}
    assert {"run", "install-peers.sh"} <= names


def test_no_pipe_ends_in_an_early_quitting_reader() -> None:
    offenders = [
        f"{p.relative_to(ROOT)}:{n}: {line.strip()}"
        for p in _pipefail_scripts()
        for n, line in enumerate(p.read_text().splitlines(), 1)
        if not line.lstrip().startswith("#") and EARLY_QUIT.search(line)
    ]
    assert offenders == []


def test_the_pattern_catches_the_failure_that_happened() -> None:
    assert EARLY_QUIT.search('v="$(pdftoppm -v 2>&1 | head -n1)"')
    assert EARLY_QUIT.search("v=$(socat -V | awk '/socat version/ {print $3; exit}')")
    fixed = "v=$(socat -V | awk '/socat version/ && !v {v = $3} END {print v}')"
    assert not EARLY_QUIT.search(fixed)
