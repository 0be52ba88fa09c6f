"""The arguments of `rumba map`; the command is ``daemon.cli.commands.map``."""

from __future__ import annotations

import argparse

from daemon.cli.choices import DEFAULT_STYLUS_DIAMETER_MM

DESCRIPTION = ("`rumba map`: the volumetric map of the linear axes (their 18 motion errors as "
               "smooth functions, with the links and setups) from one or more placements of the "
               "artefact, each a probing log with its artefact file; --predict: the volumetric "
               "error at commanded points.")


def _run(args: argparse.Namespace) -> int:
    from daemon.cli.commands.map import cmd_map

    return cmd_map(args)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("map", help="map the linear axes' motion errors from probing logs",
                       description=DESCRIPTION)
    p.add_argument("--machine", required=True, help="machine YAML")
    p.add_argument("--placement", nargs=2, action="append", metavar=("LOG", "ARTEFACT"),
                   help="a probing log and the artefact file of that placement (repeat for "
                        "each placement: its ball setup is its own, links, map and probe are "
                        "shared)")
    p.add_argument("--holdout", nargs=2, metavar=("LOG", "ARTEFACT"),
                   help="a placement kept out of the fit: its residual before / after the map")
    p.add_argument("--map", metavar="MAP.json", help="a map written by `rumba map --json` "
                   "(instead of --placement): predict from it")
    p.add_argument("--json", metavar="OUT.json", help="write the map (contracts/linear_map.py)")
    p.add_argument("--report", metavar="DIR",
                   help="write the map report into DIR: map.html, map.pdf (A4, for filing) and "
                        "map.json (the map, as --json); with --map: the report of a saved map")
    p.add_argument("--predict", metavar="POINTS.csv",
                   help="commanded points, header x_mm,y_mm,z_mm (rotary axes at zero)")
    p.add_argument("--out", metavar="PRED.csv", help="--predict: where the predictions go")
    p.add_argument("--max-degree", type=int, default=4, metavar="N",
                   help="cap of the Legendre degree per axis, chosen up to it by "
                        "cross-validation (default 4)")
    p.add_argument("--degrees", metavar="DX,DY,DZ",
                   help="fixed degrees per axis instead of the cross-validated choice")
    p.add_argument("--repeatability-um", default=None, metavar="S|SX,SY,SZ",
                   help="probing repeatability of a centre (µm); default: from the residuals")
    p.add_argument("--fixed-radius", action="store_true",
                   help="fit spheres with radius = ball + stylus radius (default: free radius)")
    p.add_argument("--stylus-diameter", type=float, default=DEFAULT_STYLUS_DIAMETER_MM,
                   metavar="MM", help=f"stylus diameter (default {DEFAULT_STYLUS_DIAMETER_MM})")
    p.add_argument("--limit-um", metavar="WARN[,FAIL]",
                   help="limits on the map's largest volumetric error (µm)")
    p.add_argument("--config", metavar="daemon.yaml",
                   help="take the limit from this machine's tolerances.volumetric_max_um "
                        "(the entry whose machine file has this machine's name)")
    p.add_argument("--store", action="store_true",
                   help="journal the map (its figures, verdict and the paths and SHA-256 of "
                        "its map file and report) in the journal of --config: rumba history, "
                        "the HMI, the fleet store, OPC UA and AQDEF show it")
    p.set_defaults(func=_run)
