"""``rumba compensate RUN --config daemon.yaml``: the controller-model changes that hold the
run's identified link errors, guarded, and what a confirmation would write (a review document,
never a program); ``--confirm --by NAME`` writes and applies them, ``--rollback`` restores the
values before the last applied compensation. Exit 0 done, 2 refused."""

from __future__ import annotations

import argparse
import asyncio

from contracts.yaml_files import ConfigError
from daemon.cli.main import UserError
from daemon.compensation import journal as cj
from daemon.compensation.apply import ApplyError, confirm, rollback
from daemon.compensation.listing import fingerprint, listing_lines, with_closing
from daemon.compensation.names import BadName, validate_by
from daemon.compensation.propose import (
    CompensationRefused,
    ControllerModelError,
    Proposal,
    is_local_linuxcnc,
    propose,
    spec_of,
    unit_of,
)
from daemon.config import DaemonConfig, load_daemon_config
from daemon.machines.setup import MachineSetup
from daemon.reports.compensation import verification_of
from daemon.reports.proposal import review_document, why_nothing, write_review
from daemon.store.journal import Store, StoreError
from identification.worth import plain


def _fmt(kind: str, model_value: float, sign: bool = True) -> str:
    f, unit = (1e3, "µm") if kind == "pivot" else (1e6, "µrad")
    return f"{plain(model_value * f, 2, sign)} {unit}"


def _link(name: str, v: float) -> str:
    # rounded to 4 decimals first, as the analysis JSON and the report round a link
    f, unit = (1e6, "µrad") if name[1] in "ABC" else (1e3, "µm")
    return f"{plain(round(v * f, 4), 2, sign=True)} {unit}"


def render(p: Proposal) -> list[str]:
    """The proposal as text: values, links, distortion."""
    plan = p.plan
    accepted = {v.name: v for v in p.values}
    refused = bool(p.refusals)
    now = p.current
    lines = [f"compensation of run {p.run_id} ({p.spec.family}), U with k = {p.coverage_k:g}:",
             f"  {'value':<14} {'address':<30} {'old':>12} {'new':>12} {'Δ':>14} {'U':>12}  "
             "status"]
    for ch in plan.changes:
        sp = p.spec.param(ch.name)
        unit = unit_of(ch.kind)[0]
        v = accepted.get(ch.name)
        old = v.old if v else now[ch.name]
        new = f"{v.new:.6g}" if v else "—"
        if v is not None:
            status = "refused" if refused else "apply"
        else:
            status = f"skipped ({p.skipped.get(ch.name, 'not applied')})"
        lines.append(f"  {ch.name:<14} {sp.address:<30} {old:>12.6g} {new:>12} "
                     f"{_fmt(ch.kind, ch.delta):>14} {_fmt(ch.kind, ch.u_expanded, False):>12}  "
                     f"{status}  [{unit}]")
    lines.append("  links        run estimate  held by changes       residual")
    for k in plan.links_identified:
        lines.append(f"  {k:<10} {_link(k, plan.links_identified[k]):>14} "
                     f"{_link(k, plan.links_compensable[k]):>14} "
                     f"{_link(k, plan.links_residual[k]):>14}")
    lines.append(f"  ({p.links_text()})")
    # the figures as the report and the HMI name and define them
    for f in p.figures():
        lines.append(f"  {f.text()} — {f.definition}")
    if p.program is not None:
        lines.append(f"what a confirmation writes ({p.program.filename}), every address as "
                     "the program writes it, in the controller's unit and sign:")
        lines += listing_lines(p.program.listing, "    ")
    elif not p.refusals:
        lines.append(why_nothing(p))
    return lines


def _setup(cfg: DaemonConfig, name: str | None, store: Store, run_id: str | None
           ) -> MachineSetup:
    if name is None:
        if run_id is None:
            raise UserError("--machine is needed without a run")
        name = store.run(run_id).machine
    setup = cfg.machines.get(name)
    if setup is None:
        raise UserError(f"{cfg.path}: no machine {name!r} (configured: "
                        f"{', '.join(cfg.machines)})")
    return setup


def _refuse(store: Store, setup: MachineSetup, run_id: str, reason: str,
            values: list[cj.ValueChange] | None = None, by: str = "") -> int:
    spec = None
    try:
        spec = spec_of(setup)
    except ConfigError:  # a broken section: refused, and journaled as such
        spec = None
    row = cj.record(store, setup.name, run_id, spec.family if spec else "", "refused",
                    values or [], confirmed_by=by, reason=reason)
    print(f"refused (journal #{row}): {reason}")
    return 2


def _link_verification(store: Store, setup: MachineSetup, run_id: str) -> None:
    """A run after the last applied compensation verifies it (its id on that journal row)."""
    last = cj.last_applied(store, setup.name)
    if last is None or last.verify_run_id or last.run_id == run_id:
        return
    if last.applied_at is not None and store.run(run_id).started_at > last.applied_at:
        cj.update(store, last.id, verify_run_id=run_id)


def _verify_after(cfg: DaemonConfig, setup: MachineSetup, store: Store, p: Proposal) -> int:
    """The verification run that follows a live write, and each link before and after (the
    run's report shows the same); its exit code is the command's."""
    if not is_local_linuxcnc(setup, p.spec):
        print(f"verify: load the program on the control first, then: rumba verify --config "
              f"{cfg.path} --machine {setup.name}")
        return 0
    from daemon.cli.commands.verify import verify  # the run's daemon machinery, when needed

    code = asyncio.run(verify(str(cfg.path), setup.name, quiet=True))
    run = store.runs(setup.name, 1)[0]
    analysis = store.analysis(run.id)
    view = verification_of(store, run, analysis) if analysis is not None else None
    if view is None:
        print(f"verification run {run.id}: {run.state} ({run.reason or run.summary})")
        return 2
    print(f"verification run {run.id} ({run.summary}):")
    for link in view.links:
        unit = "µrad" if link.unit == "urad" else "µm"
        print(f"  {link.name:<6} {link.before:+9.2f} ± {link.u_before:.2f} -> "
              f"{link.after:+9.2f} ± {link.u_after:.2f} {unit}")
    return code


def _compensate(args: argparse.Namespace, cfg: DaemonConfig, store: Store) -> int:
    if args.by is not None:  # before anything is journaled with it
        try:
            validate_by(args.by)
        except BadName as e:
            raise UserError(str(e)) from None
    again = getattr(args, "again", False)
    if again and not args.confirm:
        raise UserError("--again is a new decision to apply: give it with --confirm")
    if args.rollback:
        if not args.machine or not args.by:
            raise UserError("--rollback needs --machine and --by")
        setup = _setup(cfg, args.machine, store, None)
        try:
            w = rollback(setup, store, cfg.reports_dir, args.by)
        except CompensationRefused as e:
            return _refuse(store, setup, "", str(e), by=args.by)
        except ApplyError as e:  # journaled by rollback()
            print(f"error: {e}")
            return 2
        if w.program is not None:  # as the program writes them, every address
            print("\n".join(listing_lines(w.program.listing)))
        print(f"rolled back (journal #{w.row_id}): {w.note}")
        print(f"program: {w.path}")
        return 0
    if not args.run:
        raise UserError("give a RUN (or --rollback)")
    if args.confirm and not args.by:
        raise UserError("--confirm needs --by NAME (who confirms, recorded in the journal)")
    if args.verify and not args.confirm:
        raise UserError("--verify follows a write: give it with --confirm")
    if getattr(args, "listing", None) is not None and not args.confirm:
        raise UserError("--listing names what a confirmation writes: give it with --confirm")
    try:
        store.run(args.run)
    except StoreError as e:
        raise UserError(str(e)) from None
    setup = _setup(cfg, args.machine, store, args.run)
    try:
        p = propose(setup, store, args.run)
    except CompensationRefused as e:
        return _refuse(store, setup, args.run, str(e), by=args.by or "")
    _link_verification(store, setup, args.run)
    print("\n".join(render(p)))
    if p.refusals:
        return _refuse(store, setup, args.run, "; ".join(p.refusals), p.values, args.by or "")
    if not p.values or p.program is None:
        why = why_nothing(p)
        row = cj.record(store, setup.name, args.run, p.spec.family, "proposed", [], reason=why)
        print(f"{why} (journal #{row})")
        return 0
    seen = fingerprint(p.spec.family, p.run_id, p.program.listing)
    if args.confirm:
        try:
            w = confirm(setup, store, cfg.reports_dir, p, args.by, again=again,
                        seen=getattr(args, "listing", None))
        except CompensationRefused as e:
            return _refuse(store, setup, args.run, str(e), p.values, args.by)
        except ApplyError as e:
            print(f"error: {e}")
            return 2
        print(f"applied (journal #{w.row_id}, confirmed by {args.by}): {w.note}")
        print(f"program: {w.path}")
        if args.verify:
            return _verify_after(cfg, setup, store, p)
        return 0
    # a proposal is a review document, never a program: nothing a control could load exists
    # until a person confirms (then the program is made again and must list the same)
    command = (f"rumba compensate --config {cfg.path} --confirm {args.run} --by NAME "
               f"--listing {seen}")
    try:
        path = write_review(cfg.reports_dir, review_document(p, setup.name, command))
    except OSError as e:
        raise UserError(f"review document not written into {cfg.reports_dir}: {e}") from None
    row = cj.record(store, setup.name, args.run, p.spec.family, "proposed",
                    with_closing(p.values, p.program.values),
                    reason=f"review document {path.name}; no program exists until a person "
                           f"confirms (listing {seen})")
    print(f"proposed (journal #{row}): nothing written to the controller and no program made; "
          f"review {path}, then: {command}")
    print(f"review: {path}")
    return 0


def cmd_compensate(args: argparse.Namespace) -> int:
    cfg = load_daemon_config(args.config)
    try:
        store = Store(cfg.store_path, cfg.synchronous,  # type: ignore[arg-type]
                      source=f"{cfg.path}: store.path")
    except StoreError as e:
        raise UserError(str(e)) from None
    try:
        return _compensate(args, cfg, store)
    except ControllerModelError as e:
        raise UserError(str(e)) from None
    finally:
        store.close()
