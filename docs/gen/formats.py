"""The file formats: the probing log and the centres file (their header, columns, types and
ranges from ``contracts.probing_log`` / ``contracts.centres_file``), and the ceilings every
reader enforces (the ``MAX_*`` constants, with the comment or docstring beside them)."""

from __future__ import annotations

import ast
import importlib
import inspect

from docs.gen.text import cell, clean, code, header, table

# What each column holds: the code has the names, types and ranges; the meaning is said here
# once, and a column added to or removed from a header fails the generator until it is.
MEANING = {
    "run_id": "the run (1-64 letters, digits or `-` in the daemon's journal; names report files)",
    "seq": "touch sequence number in the run's programs (1-based); a gap is a warning naming the "
           "missing ranges",
    "t_s": "seconds since the run's first program started, one clock for every program of the "
           "run (a re-probe round's rows follow the plan's by the time that passed)",
    "repeat": "repeat of the pose in the plan; 100 × round + repeat for a re-probe of a faulty "
              "ball visit",
    "pose": "pose number of the plan (one indexation of the rotary axes)",
    "b_cmd_deg": "first rotary axis (alphabetical: A on an A/C machine), commanded, degrees",
    "c_cmd_deg": "second rotary axis, commanded, degrees",
    "ball": "ball id of the artefact file",
    "touch": "1-4 the equator diagonals, 5 the pole",
    "dir_x": "approach direction of the tool relative to the workpiece, machine frame, x",
    "dir_y": "approach direction, y",
    "dir_z": "approach direction, z",
    "x_mm": "latched X, controller coordinates, mm (a centre: the ball centre)",
    "y_mm": "latched Y, mm",
    "z_mm": "latched Z, mm",
    "b_deg": "first rotary axis as latched (or read), degrees",
    "c_deg": "second rotary axis as latched (or read), degrees",
    "feed_mm_min": "probing feed, mm/min",
    "u_um": "standard uncertainty of the centre, µm, each coordinate: on every row or on none",
}


def _columns(module: object) -> str:
    header_cols = module.HEADER
    missing = [c for c in header_cols if c not in MEANING]
    if missing:
        raise SystemExit(f"docs/gen/formats.py: describe the new column(s) {missing}")
    types = module.COLUMN_TYPES
    ranges = module.RANGES
    rows = []
    for c in header_cols:
        kind = {"str": "text", "int": "counter", "float": "number"}.get(str(types.get(c)),
                                                                      str(types.get(c)))
        low_high = ranges.get(c)
        if c == "u_um":
            low_high = (0.0, module.MAX_U_UM)
        limit = (f"{low_high[0]:g} … {low_high[1]:g}" if low_high else "")
        rows.append([code(c), kind, limit, cell(MEANING[c])])
    return table(["column", "type", "range", "meaning"], rows)


def probing_log() -> str:
    import contracts.probing_log as log

    return "\n".join([
        header("Probing log", "contracts/probing_log.py"),
        "One row per touch, as the daemon journals it and `rumba history --export` writes it; "
        "`rumba analyze --log` and `rumba gap --log` read it. The first line and the header "
        "are exactly:\n",
        f"```text\n{log.MAGIC}\n{','.join(log.HEADER)}\n```\n",
        "## Columns\n",
        _columns(log),
        f"Numbers: {clean(log.NUMBER_SYNTAX)}. Counters: {clean(log.COUNT_SYNTAX)}. Ids: at "
        f"most {log.MAX_ID_CHARS} characters. The five touches of one ball visit agree on "
        f"the latched rotary axes within {log.ROTARY_SPREAD_DEG:g}°.\n",
        "## Reading rules\n",
        _module_doc(log),
    ])


def centres_file() -> str:
    import contracts.centres_file as cf

    return "\n".join([
        header("Centres file", "contracts/centres_file.py"),
        "Ball centres measured by anything else than the touch probe (a CMM, a camera, an "
        "R-test, another program's sphere fits), one row per centre; `rumba analyze --centres` "
        "and `rumba gap --centres` read it, `rumba analyze --log … --write-centres` writes it. "
        "The first line and the header are exactly:\n",
        f"```text\n{cf.MAGIC}\n{','.join(cf.HEADER)}\n```\n",
        "Between them, optional preamble lines: `## free text` (a comment) or `# key: value` "
        f"with the keys {', '.join(code(k) for k in cf.KEYS)}; `frame` is one of "
        f"{', '.join(code(f) for f in cf.FRAMES)}.\n",
        "## Columns\n",
        _columns(cf),
        "## Reading rules\n",
        _module_doc(cf),
    ])


def _module_doc(module: object) -> str:
    doc = inspect.getdoc(module) or ""
    paragraphs = [p for p in doc.split("\n\n")[1:] if p.strip()]
    out = []
    for p in paragraphs:
        if p.lstrip().startswith("* "):
            out.append("\n".join(f"* {clean(item)}" for item in p.split("\n* ")))
        else:
            out.append(clean(p))
    return "\n\n".join(out) + "\n"


CEILINGS = [
    ("contracts.yaml_files", "MAX_YAML_BYTES", "bytes"),
    ("contracts.yaml_files", "MAX_YAML_NODES", ""),
    ("contracts.yaml_files", "MAX_YAML_DEPTH", ""),
    ("contracts.setup_types", "MAX_POSES", ""),
    ("contracts.setup_types", "MAX_TOUCHES", ""),
    ("contracts.setup_types", "MAX_BALLS", ""),
    ("programs.geometry", "MAX_SWEEP_SAMPLES", ""),
    ("programs.model", "MAX_TARGETS_BYTES", "bytes"),
    ("contracts.csv_lines", "MAX_LOG_BYTES", "bytes"),
    ("contracts.csv_lines", "MAX_LINE_BYTES", "bytes"),
    ("contracts.probing_log", "MAX_LOG_ROWS", ""),
    ("contracts.probing_log", "MAX_ID_CHARS", ""),
    ("contracts.centres_file", "MAX_CENTRE_ROWS", ""),
    ("contracts.centres_file", "MAX_U_UM", "µm"),
    ("contracts.importers.common", "MAX_IMPORT_LINES", ""),
    ("contracts.result_lines", "MAX_RESULT_MM", "mm"),
    ("contracts.result_lines", "MAX_RESULT_DEG", "°"),
    ("daemon.config", "MAX_TOKEN_FILE_BYTES", "bytes"),
    ("daemon.hmi.users", "MAX_PASSWORD", "characters"),
    ("daemon.cli.commands.sim", "MAX_PROGRAM_BYTES", "bytes"),
    ("drivers.linuxcnc.halkins", "MAX_HAL_BYTES", "bytes"),
    ("identification.plausibility", "MAX_LINK_ROTATION_RAD", "rad"),
    ("identification.plausibility", "MAX_LINK_TRANSLATION_MM", "mm"),
    ("identification.plausibility", "MAX_RESIDUAL_UM", "µm"),
    ("identification.plausibility", "MAX_RESIDUAL_RATIO", "× the noise"),
]
# What a constant bounds where the comment beside it says only why.
FALLBACK = {
    "MAX_CENTRE_ROWS": "centre rows of a centres file",
    "MAX_SWEEP_SAMPLES": "samples of 2° × 2° of one rotary index move (add an intermediate pose)",
    "MAX_PROGRAM_BYTES": "size of a program `rumba sim --run` reads",
    "MAX_TOKEN_FILE_BYTES": "size of a token file (HMI, fleet page, webhook)",
    "MAX_U_UM": "a centre's stated uncertainty `u_um`",
    "MAX_LOG_BYTES": "size of a probing log or centres file",
    "MAX_LINE_BYTES": "length of one line of a probing log or centres file",
    "MAX_LOG_ROWS": "touch rows of a probing log",
    "MAX_ID_CHARS": "characters of a run id or ball id in a log",
    "MAX_IMPORT_LINES": "non-blank lines of an instrument's file (DMIS, KinOpt)",
    "MAX_RESULT_MM": "a latched linear position (larger: a garbled record)",
    "MAX_RESULT_DEG": "a latched rotary position",
    "MAX_TARGETS_BYTES": "size of a `--targets` estimate JSON",
    "MAX_PASSWORD": "length of an HMI password",
    "MAX_HAL_BYTES": "size of a LinuxCNC INI or HAL file rumba reads or patches",
    "MAX_LINK_ROTATION_RAD": "an identified link rotation; beyond it the fit is refused as "
                             "implausible (wrong machine or artefact file?)",
    "MAX_LINK_TRANSLATION_MM": "an identified link translation (refused beyond, as above)",
    "MAX_RESIDUAL_UM": "residual RMS refused when also above the ratio below",
    "MAX_RESIDUAL_RATIO": "residual RMS over the measurement noise refused when also above the "
                          "RMS above",
}


def _constant_doc(module_name: str, name: str) -> str:
    """The docstring after ``NAME = …`` or the comment at the end of its line."""
    module = importlib.import_module(module_name)
    source = inspect.getsource(module)
    tree = ast.parse(source)
    lines = source.splitlines()
    body = tree.body
    for i, node in enumerate(body):
        targets = node.targets if isinstance(node, ast.Assign) else (
            [node.target] if isinstance(node, ast.AnnAssign) else [])
        if any(isinstance(t, ast.Name) and t.id == name for t in targets):
            nxt = body[i + 1] if i + 1 < len(body) else None
            if isinstance(nxt, ast.Expr) and isinstance(getattr(nxt, "value", None),
                                                        ast.Constant) \
                    and isinstance(nxt.value.value, str):
                return clean(nxt.value.value)
            line = lines[node.lineno - 1]
            if "  # " in line:
                return clean(line.split("  # ", 1)[1])
    return FALLBACK.get(name, "")


def ceilings() -> str:
    rows = []
    for module_name, name, unit in CEILINGS:
        value = getattr(importlib.import_module(module_name), name)
        shown = f"{value:,}".replace(",", " ") if isinstance(value, int) else f"{value:g}"
        said = _constant_doc(module_name, name)
        what = FALLBACK.get(name, "")
        what = f"{what} ({said})" if what and said and said != what else (what or said)
        rows.append([code(name), f"{shown} {unit}".strip(), cell(what), code(module_name)])
    return "\n".join([
        header("Ceilings", "the MAX_* constants of the readers"),
        "Every file and message rumba reads is bounded: beyond a ceiling it is refused with "
        "one `error:` line naming the file (and line or key), before it can exhaust memory or "
        "time.\n",
        table(["constant", "value", "what it bounds", "module"], rows),
    ])


def measured() -> str:
    """The benchmark result files (``benchmarks/results/*.md``, written by the benchmarks
    themselves), included as they are."""
    from pathlib import Path

    results = Path(__file__).resolve().parents[2] / "benchmarks" / "results"
    files = sorted(p.name for p in results.glob("*.md")) if results.is_dir() else []
    includes = "\n\n".join(f'--8<-- "benchmarks/results/{name}"' for name in files)
    return "\n".join([
        header("Measured here", "the files in benchmarks/results/"),
        "Speed and accuracy as the benchmarks measured them on the machine named with each "
        "result: the files are written by the benchmarks (`python -m benchmarks.record NAME`), "
        "with the date, the commit, the machine and its load; none is typed here. `make bench` "
        "(or `python -m benchmarks NAME`) runs them again on yours. Accuracy claims rest on "
        "Monte Carlo runs over seeds; each states its N.\n",
        includes or "No benchmark result is recorded yet.",
    ])
