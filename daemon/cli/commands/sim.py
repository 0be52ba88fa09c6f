"""``rumba sim``: the software CNC — run a program offline into a probing log, or serve it over a
transport (``--serve``, provided by simulators/serve.py when present)."""

from __future__ import annotations

import argparse
import importlib.util

from daemon.cli.main import UserError


def _serve_module():
    if importlib.util.find_spec("simulators.serve") is None:
        return None
    import simulators.serve as serve

    return serve


def main(args: argparse.Namespace) -> int:
    from simulators.faults import FaultPlan
    from simulators.truth import TruthModel

    if args.time_scale < 0:
        raise UserError("--time-scale must be >= 0")
    truth = TruthModel.from_files(args.machine, args.artefact, args.errors, args.seed)
    faults = FaultPlan.load(args.faults) if args.faults else None
    if getattr(args, "serve", None):
        serve = _serve_module()
        if serve is None:
            raise UserError("--serve is not available (simulators/serve.py missing)")
        args.truth, args.fault_plan = truth, faults
        try:
            return int(serve.serve(args) or 0)
        except serve.ServeError as e:
            raise UserError(str(e)) from None
    if args.run is None:
        raise UserError("give --run PROGRAM (offline) or --serve TRANSPORT")
    if args.dialect is None or args.log is None:
        raise UserError("--run needs --dialect and --log OUT.csv")
    return _offline(args, truth, faults)


MAX_PROGRAM_BYTES = 64 * 2**20  # the largest plan's program (20 000 touches) is a few MB


def _offline(args: argparse.Namespace, truth, faults) -> int:
    from contracts.input_files import read_bounded
    from contracts.probing_log import write_log
    from simulators.offline import aux_files, run_sync

    # a regular file of bounded size (a FIFO would block, /dev/zero never end)
    raw = read_bounded(args.run, UserError, MAX_PROGRAM_BYTES, "program")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise UserError(f"{args.run}: byte {e.start}: not UTF-8 text") from None
    run_id = args.run_id or args.run.stem
    res = run_sync(truth, text, args.dialect, files=aux_files(args.run, UserError),
                   seed=truth.seed if args.seed is None else args.seed,
                   time_scale=args.time_scale, faults=faults, run_id=run_id)
    try:
        write_log(args.log, res.rows)
    except OSError as e:
        raise UserError(f"{args.log}: cannot write: {e.strerror}") from None
    vc = res.controller
    misses = sum(not t.triggered for t in vc.touches)
    print(f"{args.run}: {res.state}; {len(vc.touches)} probing moves, {misses} without "
          f"trigger, {len(res.rows)} touches logged to {args.log}; machine time "
          f"{res.machine_time_s:.1f} s ({res.machine_time_s / 60:.1f} min), "
          f"wall {res.wall_s:.2f} s")
    if res.state != "done":
        print(f"controller alarm: {res.alarm}")
        return 1
    return 0
