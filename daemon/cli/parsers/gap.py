"""The arguments of `rumba gap`; the command is ``daemon.cli.commands.gap``."""

from __future__ import annotations

import argparse

from daemon.cli.choices import CENTRES_FORMATS, DEFAULT_STYLUS_DIAMETER_MM, GAP_SPLITS

DESCRIPTION = ("`rumba gap`: where a probing log departs from the twin, which effect explains "
               "it, how much.")


def _run(args: argparse.Namespace) -> int:
    from daemon.cli.commands.gap import cmd_gap

    return cmd_gap(args)


def _check(args: argparse.Namespace) -> None:
    from daemon.cli import arguments
    from daemon.cli.choices import GAP_FAMILIES

    if args.selfcheck:
        return
    if not ((args.log or args.centres) and args.machine and args.artefact):
        raise arguments.user_error("gap: --log (or --centres), --machine and --artefact are "
                                   "required (or --selfcheck)")
    if args.log and args.centres:
        raise arguments.user_error("gap: --log or --centres, not both")
    arguments.inputs(args, ("machine", "artefact", "log", "centres", "holdout"))
    if args.centres:
        arguments.inputs(args, ("plan",))
    arguments.parse_repeatability(args.repeatability_um)
    arguments.parse_families(args.families, GAP_FAMILIES)
    arguments.output_folder(args.json, f"--json {args.json}")
    arguments.output_folder(args.html, f"--html {args.html}")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("gap", help="sim-to-real gap diagnosis: locate, attribute, quantify",
                       description=DESCRIPTION)
    p.add_argument("--log", help="probing log (CSV) the twin is fitted on")
    p.add_argument("--centres", metavar="FILE", help="measured ball centres instead of --log: "
                   "a centres CSV or an instrument's file (--format)")
    p.add_argument("--format", default="auto", choices=CENTRES_FORMATS,
                   help="--centres (and its --holdout) file format (default: told from the file)")
    p.add_argument("--ball", default=None, help="--centres kinopt: the ball the program measured")
    p.add_argument("--plan", default=None, metavar="PLAN.yaml",
                   help="--centres dmis: the plan whose pose numbers the feature labels use")
    p.add_argument("--repeatability-um", default=None, metavar="S|SX,SY,SZ",
                   help="stated centre repeatability (µm): the noise floor of centres, and of "
                        "touches whose form residual is zero (exact, simulated)")
    p.add_argument("--holdout", help="separate probing log (or centres file, with --centres) to "
                                     "judge on (default: leave-poses-out cross-validation)")
    p.add_argument("--machine", help="machine YAML")
    p.add_argument("--artefact", help="artefact YAML")
    p.add_argument("--stylus-diameter-mm", type=float, default=None,
                   help=f"stylus ball diameter (default {DEFAULT_STYLUS_DIAMETER_MM})")
    p.add_argument("--families", help="comma list of effect families to try (default all)")
    p.add_argument("--known", action="append", metavar="FAMILY[:AXIS]",
                   help="an effect the twin already models, fitted with it on the training "
                        "data (repeatable or a comma list; a family alone = all its axes), "
                        "e.g. --known rotary_positioning:C")
    p.add_argument("--split", choices=GAP_SPLITS, default="auto",
                   help="internal held-out split without --holdout: pose (leave-one-pose-out), "
                        "time (contiguous time blocks: the honest test of drift) or auto "
                        "(time when the log's times allow it; default)")
    p.add_argument("--no-visit-scatter", action="store_true",
                   help="judge against the trigger noise (and repeats) only, without the "
                        "per-visit index and centre scatter estimated from the run")
    p.add_argument("--json", help="write the report as JSON")
    p.add_argument("--html", help="write the report as HTML")
    p.add_argument("--selfcheck", action="store_true",
                   help="simulate every library effect withheld from the twin and diagnose it")
    p.add_argument("--seeds", type=int, default=None, help="self-check seeds per case")
    p.add_argument("--full", action="store_true",
                   help="self-check on the 14-pose plan and a 49-pose grid")
    p.set_defaults(func=_run, preflight=_check)
