"""``python -m docs.gen [--check]``: write the generated reference pages under docs/reference/,
or, with ``--check``, exit 1 naming every page that differs from what the code gives now."""

from __future__ import annotations

import difflib
import sys
from collections.abc import Callable
from pathlib import Path

from docs.gen import cli, formats, maps, pages

OUT = Path(__file__).resolve().parents[1] / "reference"
PAGES: dict[str, Callable[[], str]] = {
    "commands.md": cli.render,
    "daemon-yaml.md": pages.daemon_yaml,
    "machine-file.md": pages.machine_yaml,
    "artefact-file.md": pages.artefact_yaml,
    "plan-files.md": pages.plan_yaml,
    "simulator-files.md": pages.errors_yaml,
    "probing-log.md": formats.probing_log,
    "centres-file.md": formats.centres_file,
    "ceilings.md": formats.ceilings,
    "opcua-map.md": maps.opcua,
    "modbus-map.md": maps.modbus,
    "serial-lines.md": maps.serial,
    "can-frames.md": maps.can,
    "measured.md": formats.measured,
}


def generate() -> dict[str, str]:
    return {name: make().rstrip() + "\n" for name, make in PAGES.items()}


def main(argv: list[str]) -> int:
    pages_now = generate()
    if "--check" in argv:
        stale = []
        for name, text in pages_now.items():
            path = OUT / name
            old = path.read_text(encoding="utf-8") if path.exists() else ""
            if old != text:
                diff = difflib.unified_diff(old.splitlines(), text.splitlines(),
                                            f"docs/reference/{name}", "generated now",
                                            lineterm="", n=1)
                stale.append("\n".join(list(diff)[:40]))
        if stale:
            print("the reference pages disagree with the code; run `make docs` (or "
                  "`python -m docs.gen`) and commit docs/reference/:\n" + "\n".join(stale))
            return 1
        return 0
    OUT.mkdir(parents=True, exist_ok=True)
    for name, text in pages_now.items():
        (OUT / name).write_text(text, encoding="utf-8")
    print(f"docs/reference: {len(pages_now)} pages generated")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
