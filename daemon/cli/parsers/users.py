"""The arguments of `rumba users`; the command is ``daemon.cli.commands.users``."""

from __future__ import annotations

import argparse


def _run(args: argparse.Namespace) -> int:
    from daemon.cli.commands.users import cmd_users

    return cmd_users(args)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("users", help="HMI accounts: add, passwd, remove, list")
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--config", help="daemon.yaml (its hmi.users_file)")
    where.add_argument("--file", help="the users file itself")
    acts = p.add_subparsers(dest="action", required=True, metavar="ACTION")
    add = acts.add_parser("add", help="add an account (asks for the password)")
    add.add_argument("name", help="login name: lower-case letters, digits, '_', '-'")
    add.add_argument("--role", required=True, choices=("operator", "engineer", "admin"),
                     help="operator: start/abort; engineer, admin: also confirm and roll "
                          "back compensations")
    pw = acts.add_parser("passwd", help="set a new password (signs the person's sessions out)")
    pw.add_argument("name")
    pw.add_argument("--role", choices=("operator", "engineer", "admin"),
                    help="also change the role")
    rm = acts.add_parser("remove", help="remove an account (signs its sessions out)")
    rm.add_argument("name")
    acts.add_parser("list", help="the accounts and their roles (never the hashes)")
    log = acts.add_parser("log", help="who started, aborted, confirmed or rolled back what on "
                                      "the HMI (the journal's hmi_actions; needs --config)")
    log.add_argument("--machine", help="only this machine")
    log.add_argument("--limit", type=int, default=50, help="newest N actions (default 50)")
    for q in (add, pw):
        q.add_argument("--password-stdin", action="store_true",
                       help="read the password from the first line of stdin (scripts)")
    p.set_defaults(func=_run)
