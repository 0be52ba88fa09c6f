"""Target 4: the ``rumba`` CLI end to end (``daemon.cli.main`` in-process, output captured)."""

from __future__ import annotations

import contextlib
import io
import random
import tempfile
import warnings
from pathlib import Path

from benchmarks.fuzz.common import CONFIG, EXC_NAME, Tally, run_case
from benchmarks.fuzz.probelog import EXAMPLE, mutate_log, violations
from benchmarks.fuzz.yamls import mutate
from contracts.result_lines import DIALECT_NAMES

MACHINE = CONFIG / "machines/thesis_wcbxfzyt.yaml"
ARTEFACT = CONFIG / "artefacts/thesis_4ball.yaml"
PLAN = CONFIG / "plans/thesis_ch3_7poses.yaml"


def fuzz(rng: random.Random, n: int, limit_s: float = 20.0) -> Tally:
    from benchmarks.rigs.daemon_helpers import write_daemon_yaml
    from daemon.cli.main import main

    tally = Tally("rumba CLI")
    base_log = EXAMPLE.read_text(encoding="utf-8")
    with tempfile.TemporaryDirectory(prefix="rumba-fuzz-") as tmp_s:
        tmp = Path(tmp_s)
        daemon_yaml = write_daemon_yaml(tmp)
        for i in range(n):
            cmd = rng.choice(("analyze", "analyze", "gap", "history-import", "gcode", "gcode"))
            log = tmp / f"log{i}.csv"
            ops: list[str] = []
            data = b""
            if cmd == "gcode":
                which = rng.choice(("machine", "artefact", "plan"))
                src = {"machine": MACHINE, "artefact": ARTEFACT, "plan": PLAN}[which]
                ydata, ops, _ = mutate(rng, src.read_text(encoding="utf-8"))
                fuzzed = tmp / f"{which}{i}.yaml"
                fuzzed.write_bytes(ydata)
                files = {"machine": MACHINE, "artefact": ARTEFACT, "plan": PLAN, which: fuzzed}
                argv = ["gcode", "--machine", str(files["machine"]), "--artefact",
                        str(files["artefact"]), "--plan", str(files["plan"]), "--dialect",
                        rng.choice(DIALECT_NAMES),
                        "-o", str(tmp / f"prog{i}.nc")]
                ops.insert(0, f"{which} file")
            else:
                data, ops = mutate_log(rng, base_log)
                log.write_bytes(data)
                common = ["--machine", str(MACHINE), "--artefact", str(ARTEFACT)]
                argv = {"analyze": ["analyze", "--log", str(log), *common],
                        "gap": ["gap", "--log", str(log), *common],
                        "history-import": ["history", "--config", str(daemon_yaml), "--machine",
                                           "mill1", "--import", str(log), "--no-analyse"]}[cmd]

            def case(argv: list[str] = argv, data: bytes = data, cmd: str = cmd
                     ) -> tuple[str, str]:
                out, err = io.StringIO(), io.StringIO()
                with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), \
                        warnings.catch_warnings():
                    warnings.simplefilter("default")
                    try:
                        rc = main(argv)
                    except SystemExit as e:
                        rc = e.code if isinstance(e.code, int) else 1
                text = err.getvalue()
                if EXC_NAME.search(text):
                    return "traceback", f"exit {rc}, stderr {text.strip()[-300:]!r}"
                if rc == 2:
                    errors = [ln for ln in text.splitlines() if ln.startswith("error:")]
                    if len(errors) != 1:
                        return "traceback", f"exit 2 with {len(errors)} error lines: {text!r:.300}"
                    return "clean", errors[0][:150]
                if rc != 0:
                    return "traceback", f"exit {rc}, stderr {text.strip()[-300:]!r}"
                why = violations(data) if cmd != "gcode" else []
                return ("wrong", f"exit 0 but {'; '.join(why)[:200]}") if why else ("accepted", "")

            run_case(tally, limit_s, case, lambda i=i, cmd=cmd, ops=ops:
                     f"case {i} rumba {cmd}: {'; '.join(ops)}")
            log.unlink(missing_ok=True)
    return tally
