"""Target 3: names that reach G-code (machine, artefact, ball ids, plan) → every dialect."""

from __future__ import annotations

import copy
import random
from typing import Any

import yaml

from benchmarks.fuzz.common import CONFIG, Tally, rand_text, run_case
from contracts.result_lines import DIALECT_NAMES

PAREN = {"fanuc", "haas", "linuxcnc"}  # ( … ) comments; the others use ;
INJECT = ["\n", "\r", "\x00", "\u2028", "\u0085", "(", ")", ";", "%", "'", '"', "\n%\nM30",
          ")M30(", "; M30", "\r\nG0 X0", "\t", "\x0b", "é", "٣", "B1\n", "$", "#1=2", "[", "*"]


def fuzz_name(rng: random.Random) -> str:
    r = rng.random()
    if r < 0.3:
        return rng.choice(("B", "m", "p", "")) + rng.choice(INJECT) + rng.choice(("", "x", "1"))
    if r < 0.5:
        return rng.choice(("ok", "B9", "x.y-z_")) + rng.choice(("\n", "\r\n", "\r", " "))
    if r < 0.9:
        return rand_text(rng, 20)
    return "N" * rng.choice((32, 33, 200, 10_000))


def comment_ok(line: str, name: str, dialect: str) -> bool:
    """The name sits inside exactly one closed comment of this line (case-insensitive)."""
    lo, at = line.upper(), line.upper().find(name.upper())
    if at < 0:
        return True
    if dialect in PAREN:
        opened = lo.rfind("(", 0, at)
        closed = lo.find(")", at + len(name))
        return (opened >= 0 and closed >= 0 and lo.count("(") == lo.count(")") == 1
                and ")" not in lo[opened:at])
    semi = lo.find(";")
    return 0 <= semi < at


def fuzz(rng: random.Random, n: int, limit_s: float = 10.0) -> Tally:
    from contracts.setup_files import artefact_from_dict, machine_from_dict, plan_from_dict
    from contracts.yaml_files import ConfigError
    from programs.dialects import get_dialect
    from programs.geometry import ProgramError
    from programs.toolpath import build_program

    tally = Tally("G-code names")
    docs = {k: yaml.safe_load((CONFIG / p).read_text(encoding="utf-8")) for k, p in
            (("machine", "machines/thesis_wcbxfzyt.yaml"),
             ("artefact", "artefacts/thesis_4ball.yaml"), ("plan", "plans/thesis_ch3_7poses.yaml"))}
    m, mf = machine_from_dict(docs["machine"])
    art = artefact_from_dict(docs["artefact"])
    plan = plan_from_dict(docs["plan"])
    base_prog = build_program(m, mf, art, plan)
    baseline: dict[str, tuple[int, dict[str, int], set[str]]] = {}
    for d in DIALECT_NAMES:
        dia = get_dialect(d)
        lines = dia.render(base_prog).splitlines()
        baseline[d] = (len(lines), {k: len(v.splitlines())
                                    for k, v in dia.aux_files(base_prog).items()}, set(lines))
    for i in range(n):
        field = rng.choice(("machine", "artefact", "ball", "plan"))
        name = fuzz_name(rng)
        dialect = rng.choice(DIALECT_NAMES)

        def case(field: str = field, name: str = name, dialect: str = dialect
                 ) -> tuple[str, str]:
            d: dict[str, Any] = copy.deepcopy(docs)
            if field == "ball":
                old = d["artefact"]["balls"][0]["id"]
                d["artefact"]["balls"][0]["id"] = name
                for dist in d["artefact"].get("distances") or []:
                    dist["balls"] = [name if b == old else b for b in dist["balls"]]
            else:
                d[field]["name"] = name
            try:
                mach, mfile = machine_from_dict(d["machine"])
                artefact = artefact_from_dict(d["artefact"])
                p = plan_from_dict(d["plan"])
                dia = get_dialect(dialect)
                prog = build_program(mach, mfile, artefact, p)
                text = dia.render(prog)
                aux = dia.aux_files(prog)
            except (ConfigError, ProgramError) as e:
                return "clean", str(e)[:120]
            n_lines, aux_lines, same = baseline[dialect]
            if len(text.splitlines()) != n_lines:
                return "wrong", (f"{field} name {name!r} in {dialect}: {len(text.splitlines())} "
                                 f"program lines, {n_lines} with the shipped name")
            if {k.replace(name, "B1"): len(v.splitlines()) for k, v in aux.items()} != aux_lines:
                return "wrong", f"{field} name {name!r} in {dialect}: auxiliary files changed shape"
            if name.strip():
                for line in text.splitlines():  # only the lines the name changed
                    if line not in same and field != "ball" and not comment_ok(line, name,
                                                                                dialect):
                        return "wrong", (f"{field} name {name!r} in {dialect} outside one closed "
                                         f"comment: {line[:100]!r}")
            bad = {c for c in name if not (c.isascii() and (c.isalnum() or c in "_.-"))}
            if bad:
                return "wrong", f"{field} name {name!r} accepted in {dialect} (characters {bad})"
            return "accepted", ""

        run_case(tally, limit_s, case,
                 lambda i=i, field=field, name=name, dialect=dialect:
                 f"case {i}: {field} name {name[:80]!r} dialect {dialect}")
    return tally
