"""`rumba baseline show|set MACHINE [RUN] --config daemon.yaml [--by NAME] [--override
REASON]`: drift baseline; a run that FAILed, predates a compensation or was identified against
a model the controller no longer runs is refused unless a person overrides it with a reason."""

from __future__ import annotations

import argparse

from daemon.cli.main import UserError
from daemon.compensation.baseline_check import (
    BaselineRefused,
    check_override,
    objections,
    set_baseline,
)
from daemon.compensation.names import BadName, validate_by
from daemon.config import load_daemon_config
from daemon.store import baselines
from daemon.store.journal import RunIdError, Store, StoreError


def cmd_baseline(args: argparse.Namespace) -> int:
    cfg = load_daemon_config(args.config)
    if args.machine not in cfg.machines:
        raise UserError(f"machine {args.machine!r} is not in {cfg.path} "
                        f"(machines: {', '.join(sorted(cfg.machines))})")
    try:
        store = Store(cfg.store_path, cfg.synchronous,  # type: ignore[arg-type]
                      source=f"{cfg.path}: store.path")
    except StoreError as e:
        raise UserError(str(e)) from None
    try:
        if args.action == "set":
            return _set(store, args)
        return _show(store, args.machine)
    finally:
        store.close()


def _show(store: Store, machine: str) -> int:
    cur = baselines.current(store, machine)
    print(f"{machine}: baseline " + (cur.describe() if cur else
                                     "none: drift not checked (rumba baseline set)"))
    if cur is not None and cur.note:
        print(f"  note: {cur.note}")
    wait = baselines.pending(store, machine)
    if wait is not None:
        print(f"  proposed: {wait.describe()}: {wait.note}; confirm with rumba baseline set "
              f"{machine} {wait.run_id} --by NAME")
    if cur is not None:  # a baseline set before these objections existed, or overridden
        try:
            found = objections(store, machine, cur.run_id)
        except StoreError:
            found = []
        for why in found:
            print(f"  warning: this baseline is questionable: {why}")
    return 0


def _set(store: Store, args: argparse.Namespace) -> int:
    try:
        by = validate_by(args.by, "--by", allow_unattended=False)
        override = None if args.override is None else check_override(args.override)
    except BadName as e:
        raise UserError(str(e)) from None
    run_id = args.run
    if run_id is None:
        wait = baselines.pending(store, args.machine)
        if wait is None:
            raise UserError(f"{args.machine}: no proposed baseline to confirm; name the run")
        run_id = wait.run_id
    try:
        b = set_baseline(store, args.machine, run_id, by, args.note, override)
    except BaselineRefused as e:
        print(f"refused: {e} (rumba baseline set {args.machine} {run_id} --by NAME "
              "--override REASON)")
        return 2
    except (StoreError, RunIdError) as e:
        raise UserError(str(e)) from None
    print(f"{args.machine}: baseline {b.describe()}")
    if override is not None and b.note.startswith("[OVERRIDE"):
        print(f"  overridden, journaled: {b.note}")
    return 0
