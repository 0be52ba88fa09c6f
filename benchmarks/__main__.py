"""Run every ``benchmarks/bench_*.py`` module's ``main()`` (discovered, so anyone can add one)."""

from __future__ import annotations

import importlib
import pkgutil
import sys

import benchmarks


def main(argv: list[str]) -> int:
    names = sorted(i.name for i in pkgutil.iter_modules(benchmarks.__path__)
                   if i.name.startswith("bench_"))
    if argv:
        names = [n for n in names if any(a in n for a in argv)]
    for name in names:
        print(f"== benchmarks.{name}")
        importlib.import_module(f"benchmarks.{name}").main()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
