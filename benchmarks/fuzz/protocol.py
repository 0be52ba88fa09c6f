"""Target 6: protocol garbage (Modbus slots/status, OPC UA ring, serial result/request lines)."""

from __future__ import annotations

import math
import random
import re
import time
from typing import Any

from benchmarks.fuzz.common import CONFIG, NASTY, Tally, rand_text, run_case, short
from contracts.result_lines import DIALECT_NAMES, MAX_RESULT_MM

ASCII_NAME = re.compile(r"[A-Za-z0-9_.-]{1,32}", re.ASCII)


def _job() -> Any:
    from contracts.jobs import ProgramJob
    from contracts.setup_files import load_artefact, load_machine, load_plan
    from programs.dialects import get_dialect
    from programs.toolpath import build_program

    m, mf = load_machine(CONFIG / "machines/thesis_wcbxfzyt.yaml")
    prog = build_program(m, mf, load_artefact(CONFIG / "artefacts/thesis_4ball.yaml"),
                         load_plan(CONFIG / "plans/thesis_ch3_7poses.yaml"))
    table = prog.touch_table()
    job = ProgramJob("fuzz", "", "fanuc", len(table), touches=table)
    return job, prog, get_dialect


def _hit_problem(hit: Any, expected_seq: int | None) -> str:
    """Why an accepted hit is wrong ('' when fine)."""
    if expected_seq is not None and hit.seq != expected_seq:
        return f"accepted seq {hit.seq}, expected {expected_seq}"
    for k, v in hit.axes.items():
        if not isinstance(v, float) or not math.isfinite(v) or abs(v) > MAX_RESULT_MM:
            return f"accepted axis {k} = {v!r}"
    if not isinstance(hit.triggered, bool):
        return f"triggered = {hit.triggered!r}"
    return ""


def _modbus(rng: random.Random, n: int, job: Any) -> Tally:
    from contracts.modbus_map import STATUS_WORDS, encode_slot
    from drivers.base import LinkError
    from drivers.hits import HitFactory
    from drivers.modbus.link import check_status, slot_hit

    tally = Tally("modbus slots/status")
    for i in range(n):
        regs = encode_slot(1, {"X": rng.uniform(-500, 500), "Y": rng.uniform(-500, 500),
                               "Z": rng.uniform(-500, 500), "b": rng.uniform(-90, 90),
                               "c": rng.uniform(0, 360)})
        status = i % 5 == 4
        if status:
            regs = [rng.choice((0, 1, 2, rng.randrange(65536))) for _ in range(STATUS_WORDS)]
        for _ in range(rng.randint(1, 4)):
            regs[rng.randrange(len(regs))] = rng.choice(
                (rng.randrange(65536), 0xFFFF, 0x8000, 0x7FFF, 0, 2, -1, 0x10000))
        if rng.random() < 0.05:
            regs = regs[:rng.randrange(len(regs))]

        def case(regs: list[int] = regs, status: bool = status) -> tuple[str, str]:
            try:
                if status:
                    st = check_status(regs)
                    return ("wrong", f"status accepted {st}") if any(
                        not 0 <= v <= 0xFFFF for v in st.values()) else ("accepted", "")
                hit = slot_hit(HitFactory(job), regs, 0)
            except LinkError as e:
                return "clean", str(e)[:100]
            why = _hit_problem(hit, 1)
            return ("wrong", why) if why else ("accepted", "")

        run_case(tally, 2.0, case, lambda i=i, regs=regs, status=status:
                 f"case {i} {'status' if status else 'slot'} regs={regs}")
    return tally


OPC_VALUES: list[Any] = [float("nan"), float("inf"), -float("inf"), None, "1", True, 2**70,
                         -1, 1e308, 1.5, 0, 1, 2, b"\x00", [1], 1e5 + 1, -1e5 - 1, 7.0]


def _opcua(rng: random.Random, n: int, job: Any) -> Tally:
    from contracts.opcua_space import RESULT_ROLES, RING_SLOTS
    from drivers.base import LinkError
    from drivers.hits import HitFactory
    from drivers.opcua.link import check_counter, ring_hit

    tally = Tally("opcua ring/counter")
    for i in range(n):
        rows: list[Any] = [[1.0] + [float(rng.uniform(-300, 300)) for _ in range(RING_SLOTS - 1)]
                           for _ in RESULT_ROLES]
        rows[0][0], rows[-1][0] = 1, 1  # seq 1, triggered
        for _ in range(rng.randint(1, 3)):
            r = rng.randrange(len(rows))
            if not isinstance(rows[r], list):
                continue  # already replaced by a non-array this case
            if rng.random() < 0.1:
                rows[r] = rng.choice((rows[r][:3], None, "x", rows[r] * 2))
            else:
                rows[r][0] = rng.choice(OPC_VALUES)
        counter = rng.choice((1, 1, 1, 0, -1, 1.5, float("nan"), None, "1", 10**9))
        state = rng.choice(("running", "running", "done", "bogus", None, 3))

        def case(rows: list[Any] = rows, counter: Any = counter, state: Any = state,
                 use_counter: bool = i % 4 == 3) -> tuple[str, str]:
            try:
                if use_counter:
                    got = check_counter(counter, state, 0, job.touch_count)
                    ok = isinstance(got, int) and 0 <= got <= job.touch_count
                    return ("accepted", "") if ok else ("wrong", f"counter accepted {got!r}")
                hit = ring_hit(HitFactory(job), rows, 1)
            except LinkError as e:
                return "clean", str(e)[:100]
            why = _hit_problem(hit, 1)
            return ("wrong", why) if why else ("accepted", "")

        run_case(tally, 2.0, case, lambda i=i, rows=rows, counter=counter, state=state:
                 f"case {i}: rows[*][0]={short([r[0] if isinstance(r, list) else r for r in rows])}"
                 f" counter={counter!r} state={state!r}")
    return tally


RESULT = "RUMBA 1 0 0 B1 1 1.0000 -111.1697 -91.2982 152.1619 0.0000 0.0000"


def _serial(rng: random.Random, n: int, job: Any, prog: Any, get_dialect: Any) -> Tally:
    from drivers.base import LinkError
    from drivers.serial.link import _DncProtocol, parse_request

    tally = Tally("serial lines")
    t1 = prog.touches[0]
    base_result = RESULT.replace("B1", t1.id.ball)
    bound = {d: get_dialect(d).bind(prog) for d in DIALECT_NAMES}
    for i in range(n):
        kind = rng.choice(("request", "result", "result", "bytes"))
        words = ["RUMBA", "REQUEST", "mill1"] if kind == "request" else base_result.split(" ")
        for _ in range(rng.randint(1, 3)):
            k = rng.randrange(len(words))
            words[k] = rng.choice((rng.choice(NASTY), rand_text(rng, 8), words[k] + "\n",
                                   words[k].lower(), "٣", "1_0", "x" * 40))
        line = rng.choice((" ", "  ", "\t", "\u2028", "\u00a0")).join(words) \
            if rng.random() < 0.3 else " ".join(words)
        dialect = rng.choice(list(bound))
        raw = bytes(rng.randrange(256) for _ in range(rng.randint(0, 300)))

        def case(kind: str = kind, line: str = line, dialect: str = dialect,
                 raw: bytes = raw) -> tuple[str, str]:
            if kind == "bytes":
                proto = _DncProtocol()
                proto.running = rng.random() < 0.5
                proto.data_received(raw + b"\n")
                return "accepted", ""
            try:
                if kind == "request":
                    m = parse_request(line)
                    if m is not None and not ASCII_NAME.fullmatch(m):
                        return "wrong", f"request machine {m!r} accepted"
                    return ("accepted" if m else "clean"), ""
                hit = bound[dialect].parse_result(line)
            except (ValueError, LinkError) as e:
                return "clean", str(e)[:100]
            if hit is None:
                return "clean", "not a result line"
            nonascii = {c for c in line if c.isdigit() and not c.isascii()}
            tokens = line.split()
            underscore = [w for k, w in enumerate(tokens) if k != 4 and "_" in w]
            if nonascii or underscore:
                return "wrong", (f"{dialect}: result line with "
                                 f"{nonascii or underscore} accepted")
            why = _hit_problem(hit, None)
            if not why and any(c in line for c in "\r\u2028\x00"):  # "\n" cannot reach it
                why = "line break / NUL inside an accepted result line"
            return ("wrong", f"{dialect}: {why}") if why else ("accepted", "")

        run_case(tally, 2.0, case, lambda i=i, kind=kind, line=line, dialect=dialect, raw=raw:
                 f"case {i} {kind} {dialect}: "
                 + (f"bytes={raw[:60]!r}" if kind == "bytes" else f"{line!r}"))
    return tally


def fuzz(rng: random.Random, n: int) -> list[Tally]:
    job, prog, get_dialect = _job()
    third = max(n // 3, 1)
    out = []
    for run in (lambda: _modbus(rng, third, job), lambda: _opcua(rng, third, job),
                lambda: _serial(rng, n - 2 * third, job, prog, get_dialect)):
        t0 = time.perf_counter()
        tally = run()
        tally.seconds = time.perf_counter() - t0
        out.append(tally)
    return out
