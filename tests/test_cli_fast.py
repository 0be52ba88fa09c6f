"""The command line stays light (issue 19): what parser, help and analyze import; the fast table."""

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
# scipy.optimize is the analysis' own now (issue 21's REML of the visit scatter, issue 22's
# warm-up τ profile); scipy.stats (~1 s to import) and the I/O stacks stay out of analyze
NOT_FOR_ANALYZE = ("scipy.stats", "matplotlib", "aiohttp", "asyncua", "pymodbus")


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
    from contracts.importers import FORMATS
    from contracts.result_lines import DIALECT_NAMES
    from identification.gap.split import SPLITS
    from programs.dialects import DIALECTS

    assert choices.CENTRES_FORMATS == FORMATS
    assert choices.CENTRES_FRAMES == FRAMES
    assert choices.GAP_SPLITS == SPLITS
    assert choices.DIALECT_NAMES == DIALECT_NAMES
    assert tuple(sorted(DIALECTS)) == choices.GCODE_DIALECTS


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
