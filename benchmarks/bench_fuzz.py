"""Fuzz campaign: every input surface with seeded random mutations, outcomes per target."""

from __future__ import annotations

import os
import random
import sys
import time
import warnings
from collections.abc import Callable

from benchmarks.fuzz.common import BAD, ROOT, Tally

# Share of the total case count per target (protocol is split three ways inside).
WEIGHTS = {"probelog": 0.22, "yamls": 0.22, "gcode": 0.10, "cli": 0.06, "hmi": 0.15,
           "protocol": 0.25, "inputs": 0.20}
DEFAULT_CASES = 2500
TARGETS = ("probelog", "yamls", "gcode", "cli", "hmi", "protocol", "inputs")


def _arg(name: str, env: str, default: int | None) -> int | None:
    argv = sys.argv[1:]
    for k, a in enumerate(argv):
        if a == f"--{name}" and k + 1 < len(argv):
            return int(argv[k + 1])
        if a.startswith(f"--{name}="):
            return int(a.split("=", 1)[1])
    value = os.environ.get(env)
    return int(value) if value else default


def _targets() -> list[str]:
    value = os.environ.get("RUMBA_FUZZ_TARGETS", "")
    argv = sys.argv[1:]
    if "--targets" in argv and argv.index("--targets") + 1 < len(argv):
        value = argv[argv.index("--targets") + 1]
    chosen = [t for t in value.split(",") if t] or list(TARGETS)
    unknown = set(chosen) - set(TARGETS)
    if unknown:
        raise SystemExit(f"unknown fuzz target(s) {sorted(unknown)}; known: {', '.join(TARGETS)}")
    return chosen


def _runner(name: str) -> Callable[[random.Random, int], Tally | list[Tally]]:
    import importlib

    return importlib.import_module(f"benchmarks.fuzz.{name}").fuzz  # type: ignore[no-any-return]


def report(tallies: list[Tally], seed: int, wall_s: float, targets: str = "") -> int:
    """Print the table and the reproducers; the number of bad outcomes in all."""
    head = (f"{'target':<22}{'cases':>7}{'accepted':>9}{'clean':>7}{'traceb.':>8}{'hangs':>6}"
            f"{'wrong':>6}{'w.ref':>6}{'time s':>8}")
    print(head)
    print("-" * len(head))
    total = Tally("TOTAL")
    for t in tallies:
        print(f"{t.target:<22}{t.tried:>7}{t.accepted:>9}{t.clean:>7}{t.bad['traceback']:>8}"
              f"{t.bad['hang']:>6}{t.bad['wrong']:>6}{t.bad['refusal']:>6}{t.seconds:>8.1f}")
        total.tried += t.tried
        total.accepted += t.accepted
        total.clean += t.clean
        for k in BAD:
            total.bad[k] += t.bad[k]
    print("-" * len(head))
    print(f"{'TOTAL':<22}{total.tried:>7}{total.accepted:>9}{total.clean:>7}"
          f"{total.bad['traceback']:>8}{total.bad['hang']:>6}{total.bad['wrong']:>6}"
          f"{total.bad['refusal']:>6}{wall_s:>8.1f}")
    print(f"targets: tracebacks 0, hangs 0, wrong acceptances 0 (wrong), wrong refusals 0 "
          f"(w.ref); seed {seed} "
          f"(rerun: python -m benchmarks.bench_fuzz --seed {seed} --cases {total.tried}"
          f"{f' --targets {targets}' if targets else ''})")
    for t in tallies:
        if t.notes:
            for k, v in sorted(t.notes.items()):
                print(f"  [{t.target}] {k}: {v}")
        for outcome in BAD:
            for repro in t.cases[outcome]:
                print(f"  [{t.target}] {outcome.upper()}: {repro}")
        shown = {r for o in BAD for r in t.cases[o]}
        for kind, repro in t.kinds.items():
            if repro not in shown:
                print(f"  [{t.target}] other kind — {kind}: {repro}")
    return sum(total.bad.values())


def main() -> None:
    sys.path.insert(0, str(ROOT))
    seed = _arg("seed", "RUMBA_FUZZ_SEED", None)
    if seed is None:
        seed = random.SystemRandom().randrange(1 << 31)
    cases = _arg("cases", "RUMBA_FUZZ_CASES", DEFAULT_CASES) or DEFAULT_CASES
    chosen = _targets()
    share = sum(WEIGHTS[t] for t in chosen)
    print(f"fuzz campaign: seed {seed}, {cases} cases over {', '.join(chosen)}")
    tallies: list[Tally] = []
    t_all = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for name in chosen:
            n = max(1, round(cases * WEIGHTS[name] / share))
            rng = random.Random(seed * 101 + TARGETS.index(name))  # reproducible alone
            t0 = time.perf_counter()
            got = _runner(name)(rng, n)
            done = got if isinstance(got, list) else [got]
            spent = time.perf_counter() - t0
            if len(done) == 1:
                done[0].seconds = spent
            tallies += done
            print(f"  {name}: {sum(t.tried for t in done)} cases in {spent:.1f} s", flush=True)
    subset = ",".join(chosen) if len(chosen) < len(TARGETS) else ""
    bad = report(tallies, seed, time.perf_counter() - t_all, subset)
    print(f"fuzz: {'PASS' if bad == 0 else 'FAIL'} ({bad} bad outcomes)")


if __name__ == "__main__":
    main()
