"""The arguments of `rumba analyze`; the command is ``daemon.cli.commands.analyze``."""

from __future__ import annotations

import argparse

from daemon.cli.choices import CENTRES_FORMATS, CENTRES_FRAMES, DEFAULT_STYLUS_DIAMETER_MM

DESCRIPTION = ("`rumba analyze`: identify setup + link errors from a probing log or measured "
               "centres, print a summary, write JSON.")


def _run(args: argparse.Namespace) -> int:
    from daemon.cli.commands.analyze import cmd_analyze

    return cmd_analyze(args)


def _check(args: argparse.Namespace) -> None:
    from daemon.cli import arguments

    arguments.inputs(args, ("log", "centres", "machine", "artefact"))
    if args.centres:
        arguments.inputs(args, ("plan",))
    arguments.parse_poses(args.validate_poses)
    arguments.parse_repeatability(args.repeatability_um)
    if args.write_centres and not args.log:
        raise arguments.user_error("--write-centres: needs --log (the centres of its touches)")
    arguments.output_folder(args.json, f"--json {args.json}")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("analyze", help="identify setup and link errors from a probing log",
                              description=DESCRIPTION)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--log", help="probing-log CSV (rumba-probing-log v1)")
    src.add_argument("--centres", metavar="FILE", help="measured ball centres: a centres CSV "
                     "(rumba-centres v1) or an instrument's file (--format)")
    p.add_argument("--format", default="auto", choices=CENTRES_FORMATS,
                   help="--centres file format (default: told from the file)")
    p.add_argument("--frame", default=None, choices=CENTRES_FRAMES,
                   help="--centres: frame of the centres (default: the file's; instrument = "
                        "a rigid motion of the machine axes, estimated with the setup)")
    p.add_argument("--ball", default=None, help="--centres kinopt: the ball the program measured")
    p.add_argument("--plan", default=None, metavar="PLAN.yaml",
                   help="--centres dmis: the plan whose pose numbers the feature labels use")
    p.add_argument("--machine", required=True, help="machine YAML")
    p.add_argument("--artefact", required=True, help="artefact YAML")
    p.add_argument("--validate-poses", default=None, metavar="LIST",
                   help="comma list of pose numbers (log's pose column) held out for validation")
    p.add_argument("--links", default="all", metavar="all|none|LIST",
                   help="link errors to estimate: the identifiable set (all), none (setup only) "
                        "or a comma list of ISO names")
    p.add_argument("--fixed-radius", action="store_true",
                   help="fit spheres with radius = ball + stylus radius (default: free radius)")
    p.add_argument("--stylus-diameter", type=float, default=DEFAULT_STYLUS_DIAMETER_MM,
                   metavar="MM", help="stylus diameter for the radius health figure and "
                   f"--fixed-radius (default {DEFAULT_STYLUS_DIAMETER_MM})")
    p.add_argument("--repeatability-um", default=None, metavar="S|SX,SY,SZ",
                   help="probing repeatability of a centre (µm) for the uncertainties, e.g. "
                        "0.66,0.98,0.44 (thesis §3.4); default: from the residuals")
    p.add_argument("--json", default=None, metavar="OUT.json", help="write the results as JSON")
    p.add_argument("--write-centres", default=None, metavar="OUT.csv",
                   help="--log: also write its centres (sphere fits) as a centres CSV")
    p.set_defaults(func=_run, preflight=_check)
