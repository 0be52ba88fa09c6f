"""Time and peak memory of reading large probing logs, run by hand or by ``make bench``:

    .venv/bin/python -m benchmarks probelog
    .venv/bin/python benchmarks/bench_probelog.py [--lines 100000 1000000] [--module FILE.py]

Each measurement runs ``read_log`` in a fresh interpreter on a generated log of N touch rows
(4 balls × 5 touches per pose, poses and repeats counted up, ~190 bytes a row) and reports the
wall time and the peak RSS above the interpreter's RSS after the imports. ``--module`` reads
with another copy of ``contracts/probing_log.py`` (e.g. ``git show
HEAD~1:contracts/probing_log.py``) for a before/after comparison. A log over the reader's
ceilings is expected to be refused quickly.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

_CHILD = r"""
import importlib.util, json, resource, sys, time, warnings
sys.path.insert(0, sys.argv[3])
from identification.model import Artefact  # noqa: F401  (imports before the RSS baseline)
from contracts.setup_files import load_artefact
import os
if os.path.samefile(sys.argv[2], os.path.join(sys.argv[3], "contracts", "probing_log.py")):
    import contracts.probing_log as mod
    from daemon.analysis.touch_centres import rows_to_centres
else:  # an older probelog.py (before the touch-centres split it held rows_to_centres)
    spec = importlib.util.spec_from_file_location("probelog_under_test", sys.argv[2])
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    rows_to_centres = mod.rows_to_centres
art = load_artefact(sys.argv[4])
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
t0 = time.perf_counter()
try:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rows = mod.read_log(sys.argv[1], art)
        t1 = time.perf_counter()
        n = len(rows_to_centres(rows, art, 3.0).centres)
    outcome = f"{len(rows)} rows, {n} centres; of which centres {time.perf_counter() - t1:.2f} s"
except Exception as e:  # a refusal is a result here
    outcome = f"refused: {str(e)[-90:]}"
dt = time.perf_counter() - t0
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(json.dumps({"s": dt, "peak_mib": (peak - base) / 1024, "outcome": outcome}))
"""


def write_big_log(path: Path, n: int) -> int:
    """A valid log of ``n`` touch rows (one run, touches on spheres); returns its size."""
    h = 0.5**0.5
    dirs = [(h, h, 0.0), (-h, h, 0.0), (-h, -h, 0.0), (h, -h, 0.0), (0.0, 0.0, -1.0)]
    r = 15.5  # ball + stylus radius, mm
    with path.open("w", encoding="utf-8") as f:
        f.write("# rumba-probing-log v1\nrun_id,seq,t_s,repeat,pose,b_cmd_deg,c_cmd_deg,ball,"
                "touch,dir_x,dir_y,dir_z,x_mm,y_mm,z_mm,b_deg,c_deg,feed_mm_min\n")
        for i in range(n):
            group, touch = divmod(i, 5)
            pose_all, ball = divmod(group, 4)
            repeat, pose = divmod(pose_all, 1000)
            d = dirs[touch]
            x = 100.0 + pose * 0.01 - d[0] * r
            y, z = -50.0 + ball * 40 - d[1] * r, -200.0 - d[2] * r
            f.write(f"bench,{i + 1},{i * 4.0 + 0.125},{repeat},{pose},30.0,60.0,B{ball + 1},"
                    f"{touch + 1},{d[0]!r},{d[1]!r},{d[2]!r},{x!r},{y!r},{z!r},30.0,60.0,300.0\n")
    return path.stat().st_size


def measure(log: Path, module: Path) -> dict:
    out = subprocess.run(
        [sys.executable, "-c", _CHILD, str(log), str(module), str(ROOT),
         str(ROOT / "config/artefacts/thesis_4ball.yaml")],
        capture_output=True, text=True)
    if out.returncode:
        raise RuntimeError(out.stderr.strip().splitlines()[-1])
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lines", type=int, nargs="+", default=[100_000, 1_000_000])
    ap.add_argument("--module", type=Path, default=ROOT / "contracts/probing_log.py")
    args = ap.parse_args([] if argv is None else argv)
    with tempfile.TemporaryDirectory(prefix="bench_probelog_") as tmp:
        for n in args.lines:
            log = Path(tmp) / f"log_{n}.csv"
            size = write_big_log(log, n)
            r = measure(log, args.module)
            print(f"read_log {n:>9,} rows ({size / 2**20:7.1f} MiB): {r['s']:8.2f} s, "
                  f"peak +{r['peak_mib']:8.1f} MiB RSS — {r['outcome']}", flush=True)
            log.unlink()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
