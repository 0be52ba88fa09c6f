"""The command reference: every ``rumba`` subcommand and option, read from the argument parsers
(``daemon.cli.parsers``) as ``rumba --help`` builds them."""

from __future__ import annotations

import argparse
import os

from docs.gen.text import cell, clean, code, header, table


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _helps(parser: argparse.ArgumentParser) -> dict[str, str]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return {a.dest: a.help or "" for a in action._choices_actions}
    return {}


def _complete(parser: argparse.ArgumentParser) -> None:
    if hasattr(parser, "_complete"):  # daemon.cli.parsers.Parser adds heavy options lazily
        parser._complete()


def _value(action: argparse.Action) -> str:
    if action.nargs == 0:
        return ""
    if action.choices is not None and not isinstance(action, argparse._SubParsersAction):
        return " \\| ".join(code(c) for c in action.choices)
    metavar = action.metavar or (action.dest.upper() if action.option_strings else action.dest)
    return code(metavar if isinstance(metavar, str) else " ".join(metavar))


def _default(action: argparse.Action) -> str:
    if action.required:
        return "required"
    if action.nargs == 0 or action.default is None or action.default is False \
            or action.default in (argparse.SUPPRESS, ""):
        return ""
    if isinstance(action.default, list) and not action.default:
        return ""
    return code(action.default)


def _options(parser: argparse.ArgumentParser) -> str:
    formatter = parser._get_formatter()
    rows = []
    for action in parser._actions:
        if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
            continue
        names = ", ".join(code(o) for o in action.option_strings) or code(action.dest)
        text = formatter._expand_help(action) if action.help else ""
        rows.append([names, _value(action), _default(action), cell(text)])
    if not rows:
        return ""
    return table(["option", "value", "default", "what"], rows)


def _command(path: str, parser: argparse.ArgumentParser, help_text: str, level: int) -> str:
    _complete(parser)
    out = [f"{'#' * level} {path}\n"]
    if help_text:
        out.append(f"{clean(help_text)[0].upper()}{clean(help_text)[1:]}.\n")
    if parser.description and clean(parser.description) != clean(help_text):
        out.append(clean(parser.description) + "\n")
    usage = parser.format_usage().removeprefix("usage: ").rstrip()
    usage = "\n".join(line.removeprefix(" " * len("usage: ")) for line in usage.split("\n"))
    out.append(f"```text\n{usage}\n```\n")
    options = _options(parser)
    if options:
        out.append(options)
    if parser.epilog:
        out.append(clean(parser.epilog) + "\n")
    subs, helps = _subparsers(parser), _helps(parser)
    for name, sub in subs.items():
        out.append(_command(f"{path} {name}", sub, helps.get(name, ""), level + 1))
    return "\n".join(out)


def render() -> str:
    os.environ["COLUMNS"] = "96"  # argparse wraps usage at the terminal's width: fix it
    from daemon.cli.main import build_parser

    parser = build_parser()
    subs, helps = _subparsers(parser), _helps(parser)
    out = [header("Commands", "the argument parsers in daemon/cli/parsers/")]
    out.append("Every `rumba` command and option, as `rumba COMMAND --help` shows it. Exit codes "
               "of every command: 0 done (for `rumba verify`: PASS or WARN), 1 a verdict of FAIL "
               "(`rumba verify`) or a target missed (`rumba plan --max-time`), 2 an expected "
               "failure (bad file, unknown key, unreachable controller, refusal) printed as one "
               "`error: …` line, 70 a defect of rumba-cnc (one `internal error` line naming a "
               "crash file with the traceback), 130 / 143 stopped by SIGINT / SIGTERM.\n")
    out.append(table(["command", "what"],
                     [[f"[`rumba {n}`](#rumba-{n})", cell(helps.get(n, ""))] for n in subs]))
    for name, sub in subs.items():
        out.append(_command(f"rumba {name}", sub, helps.get(name, ""), 2))
    return "\n".join(out)
