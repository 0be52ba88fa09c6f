"""The command line stays light: what parser, help and analyze import; the fast table."""

# behavioural checks only, no timings: those are benchmarks/bench_cli.py

from __future__ import annotations

import io
import json
import subprocess
import sys
from pathlib import Path

import pytest
from rich.console import Console

from daemon.cli import choices
from daemon.cli.main import build_parser
from daemon.cli.tables import make_table, print_long_table

ROOT = Path(__file__).resolve().parents[1]
CFG = ROOT / "config"
HEAVY = ("numpy", "scipy", "matplotlib", "aiohttp", "asyncua", "pymodbus", "pydantic",
         "pydantic_core", "yaml", "rich", "serial", "can")
# the REML of the visit scatter (Newton, identification/visit_reml.py) and the warm-up τ
# profile (Brent, identification/brent.py) need no scipy: analyze imports none of it (0.4 s
# CPU for scipy.optimize, ~1 s for scipy.stats), nor the I/O stacks
NOT_FOR_ANALYZE = ("scipy", "matplotlib", "aiohttp", "asyncua", "pymodbus")


def _imported(code: str, names: tuple[str, ...]) -> list[str]:
    """Which of ``names`` a fresh interpreter has imported after running ``code``."""
    probe = (f"{code}\nimport sys\n"
             f"print(','.join(n for n in {names!r} if n in sys.modules))")
    out = subprocess.run([sys.executable, "-c", probe], cwd=ROOT, capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    last = out.stdout.strip().splitlines()[-1] if out.stdout.strip() else ""
    return [n for n in last.split(",") if n]


def test_building_the_parser_imports_no_heavy_module():
    assert _imported("import daemon.cli.main as m\nm.build_parser()", HEAVY) == []


M_, A_ = str(CFG / "machines/thesis_wcbxfzyt.yaml"), str(CFG / "artefacts/thesis_4ball.yaml")
LOG_ = str(CFG / "examples/thesis_annexB_14poses.csv")
PLAN_ = str(CFG / "plans/thesis_annexB_14poses.yaml")
# argument errors a command finds before it imports its work (daemon/cli/arguments.py), with
# the message it gave after loading everything
LATE_ERRORS = [
    (["analyze", "--log", "no-such.csv", "--machine", M_, "--artefact", A_],
     "error: no-such.csv: cannot read: No such file or directory"),
    (["analyze", "--log", LOG_, "--machine", str(CFG), "--artefact", A_],
     f"error: {CFG}: is a directory: expected a regular file"),
    (["analyze", "--log", LOG_, "--machine", M_, "--artefact", A_, "--validate-poses", "3,x"],
     "error: --validate-poses: expected a comma list of pose numbers as in the log's pose "
     "column, got '3,x'"),
    (["analyze", "--log", LOG_, "--machine", M_, "--artefact", A_, "--repeatability-um", "0"],
     "error: --repeatability-um: expected one or three positive numbers (x,y,z centre std in "
     "µm), got '0'"),
    (["analyze", "--log", LOG_, "--machine", M_, "--artefact", A_, "--json", "/no/such/a.json"],
     "error: --json /no/such/a.json: cannot write: No such file or directory"),
    (["analyze", "--centres", LOG_, "--machine", M_, "--artefact", A_, "--write-centres", "c"],
     "error: --write-centres: needs --log (the centres of its touches)"),
    (["gap", "--log", LOG_, "--machine", M_, "--artefact", A_, "--families", "heat"],
     "error: --families: unknown ['heat']; expected a comma list of thermal_drift, "
     "linear_scale, straightness, angular_motion, rotary_positioning, rotary_error_motion, "
     "gravity_sag, probe_pretravel, artefact_instability"),
    (["gap", "--machine", M_, "--artefact", A_],
     "error: gap: --log (or --centres), --machine and --artefact are required (or "
     "--selfcheck)"),
    (["gap", "--log", LOG_, "--holdout", "no-such.csv", "--machine", M_, "--artefact", A_],
     "error: no-such.csv: cannot read: No such file or directory"),
    (["gcode", "--machine", M_, "--artefact", A_, "--plan", "no-such.yaml", "--dialect",
      "fanuc"], "error: no-such.yaml: cannot read: No such file or directory"),
    (["gcode", "--machine", M_, "--artefact", A_, "--plan", PLAN_, "--dialect", "fanuc", "-o",
      "/no/such/p.nc"], "error: /no/such/p.nc: cannot write: No such file or directory"),
    (["plan", "--machine", M_, "--artefact", A_, "--target", "no-such.yaml"],
     "error: no-such.yaml: cannot read: No such file or directory"),
    (["verify", "--config", "no-such.yaml", "--machine", "m"],
     "error: no-such.yaml: cannot read: No such file or directory"),
    (["run", "--config", "no-such.yaml"],
     "error: no-such.yaml: cannot read: No such file or directory"),
    (["history", "--config", "no-such.yaml"],
     "error: no-such.yaml: cannot read: No such file or directory"),
]


@pytest.mark.parametrize(("argv", "message"), LATE_ERRORS)
def test_argument_errors_are_answered_before_the_work_is_imported(argv, message):
    code = ("import contextlib, io, sys\nimport daemon.cli.main as m\nerr = io.StringIO()\n"
            "with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):\n"
            f"    rc = m.main({argv!r})\n"
            "print(rc, err.getvalue().strip(), file=sys.stderr)")
    probe = (f"{code}\nprint(','.join(n for n in {HEAVY!r} if n in sys.modules))")
    out = subprocess.run([sys.executable, "-c", probe], cwd=ROOT, capture_output=True,
                         text=True, timeout=120)
    assert out.stderr.strip() == f"2 {message}"
    assert out.stdout.strip() == ""  # no heavy module


@pytest.mark.parametrize("argv", [["--help"], ["analyze", "--help"], ["sim", "--help"],
                                  ["gap", "--split", "nope"], ["analyze"]])
def test_help_and_argument_errors_import_no_heavy_module(argv):
    code = ("import contextlib, io\nimport daemon.cli.main as m\n"
            "with contextlib.redirect_stdout(io.StringIO()), "
            "contextlib.redirect_stderr(io.StringIO()):\n"
            f"    try:\n        m.main({argv!r})\n    except SystemExit:\n        pass")
    assert _imported(code, HEAVY) == []


def test_analyze_imports_only_what_it_needs(tmp_path: Path):
    code = ("import contextlib, io\nimport daemon.cli.main as m\n"
            "with contextlib.redirect_stdout(io.StringIO()):\n"
            f"    assert m.main(['analyze', '--log', "
            f"{str(CFG / 'examples/thesis_annexB_14poses.csv')!r}, '--machine', "
            f"{str(CFG / 'machines/thesis_wcbxfzyt.yaml')!r}, '--artefact', "
            f"{str(CFG / 'artefacts/thesis_4ball.yaml')!r}, '--json', "
            f"{str(tmp_path / 'a.json')!r}]) == 0")
    assert _imported(code, NOT_FOR_ANALYZE) == []
    assert (tmp_path / "a.json").exists()


def test_sim_parser_gets_the_serve_options_when_used():
    args = build_parser().parse_args(["sim", "--machine", "m.yaml", "--artefact", "a.yaml",
                                      "--serve", "serial", "--baud", "9600"])
    assert args.serve == "serial" and args.baud == 9600


def test_light_copies_equal_their_sources():
    from contracts.centres_file import FRAMES
    from contracts.dialects import DIALECTS
    from contracts.importers import FORMATS
    from identification.effects import FAMILIES
    from identification.gap.split import SPLITS

    assert choices.CENTRES_FORMATS == FORMATS
    assert choices.CENTRES_FRAMES == FRAMES
    assert choices.GAP_SPLITS == SPLITS
    assert choices.GAP_FAMILIES == FAMILIES
    assert tuple(DIALECTS) == choices.DIALECT_NAMES  # the dialect records, in their order
    # the program-writer families `rumba gcode` lists first (haas, a fanuc variant, after them)
    assert tuple(sorted({r.family for r in DIALECTS.values()})) == choices.GCODE_DIALECTS


def _both(columns, rows, **console) -> tuple[str, str]:
    fast, slow = io.StringIO(), io.StringIO()
    print_long_table(Console(file=fast, **console), "A title (µm)", columns, rows)
    Console(file=slow, **console).print(make_table("A title (µm)", columns, rows))
    return fast.getvalue(), slow.getvalue()


ROWS = [(str(i) + (" r1" if i % 7 == 0 else ""), f"{-45 + i:g}", f"{i * 15:g}", "—",
         f"{104.0 + i / 7:.2f}", "µ° ok") for i in range(40)]
COLUMNS = [("pose", "right"), ("b°", "right"), ("c°", "right"), ("|relocalisation| µm", "right"),
           ("value", "left"), ("note", "left")]


@pytest.mark.parametrize("width", [200, 80, 72, 40])
@pytest.mark.parametrize("terminal", [False, True])
def test_fast_table_is_rich_byte_for_byte(width, terminal):
    fast, slow = _both(COLUMNS, ROWS, width=width, force_terminal=terminal,
                       color_system="truecolor" if terminal else None)
    assert fast == slow


@pytest.mark.parametrize("rows", [[], [("[bold]x", "1", "2", "3", "4", "5")],
                                  [("a\nb", "1", "2", "3", "4", "5")],
                                  [(":smile:", "1", "2", "3", "4", "5")],
                                  [(" lead", "1", "2", "3", "4", "5")]])
def test_cells_rich_would_change_go_through_rich(rows):
    fast, slow = _both(COLUMNS, rows, width=100)
    assert fast == slow


def test_the_analysis_is_built_as_its_json(tmp_path: Path):
    """Built once (no JSON round trip): typed as reading its own JSON back would type it."""
    from daemon.analysis.result import Analysis
    from daemon.cli.commands.analyze import run_analysis

    r = run_analysis(CFG / "examples/thesis_annexB_14poses.csv",
                     CFG / "machines/thesis_wcbxfzyt.yaml", CFG / "artefacts/thesis_4ball.yaml",
                     validate_poses=[3, 4, 5, 7, 9, 10, 11])
    text = json.dumps(r.to_json(), indent=1, ensure_ascii=False)
    back = Analysis.from_json(json.loads(text))
    assert back == r
    assert json.dumps(back.to_json(), indent=1, ensure_ascii=False) == text
