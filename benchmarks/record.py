"""``python -m benchmarks.record NAME …``: run benchmarks and keep what they printed as a dated
Markdown file ``benchmarks/results/<NAME>.md`` — date, commit, machine, load before and after
— which the manual includes as it is (its "Measured here" page), so no figure is typed by hand.
"""

from __future__ import annotations

import datetime
import io
import os
import platform
import re
import subprocess
import sys
import time
from contextlib import redirect_stdout
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"


def _cpu() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, text=True,
                              capture_output=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def _load() -> str:
    return " / ".join(f"{x:.1f}" for x in os.getloadavg())


def record(name: str) -> Path:
    """Run ``benchmarks.<name>``'s main() and write its output with where and when it ran."""
    import importlib

    module = importlib.import_module(f"benchmarks.{name}")
    load_before, started = _load(), datetime.datetime.now(datetime.UTC)
    t0 = time.monotonic()
    buffer = io.StringIO()
    with redirect_stdout(buffer):
        module.main()
    wall = time.monotonic() - t0
    doc = re.sub(r"\s*\(issues? \d+[^)]*\)", "", (module.__doc__ or name).strip().split("\n\n")[0])
    doc = " ".join(doc.split())
    text = (f"### `{name}`\n\n{doc}\n\n"
            f"Run {started:%Y-%m-%d %H:%M} UTC, commit `{_commit()}`, {_cpu()}, "
            f"{os.cpu_count()} logical CPUs, Python {platform.python_version()}; load average "
            f"(1 / 5 / 15 min) {load_before} before, {_load()} after; {wall:.0f} s wall. "
            "Each line states its own N (repeats, medians).\n\n"
            f"```text\n{buffer.getvalue().rstrip()}\n```\n")
    RESULTS.mkdir(exist_ok=True)
    out = RESULTS / f"{name}.md"
    out.write_text(text, encoding="utf-8")
    return out


def main(argv: list[str]) -> int:
    if not argv:
        print("usage: python -m benchmarks.record BENCH_NAME …", file=sys.stderr)
        return 2
    for name in argv:
        print(f"wrote {record(name).relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
