"""`rumba users`: the HMI accounts file (``daemon.hmi.users``) — add, passwd, remove, list."""

from __future__ import annotations

import argparse
import getpass
import sys
from pathlib import Path

from daemon.cli.main import UserError
from daemon.hmi.users import User, UsersError, check_name, hash_password, read_users, write_users


def users_path(args: argparse.Namespace) -> Path:
    """``--file``, or the ``hmi.users_file`` of ``--config``."""
    if args.file:
        return Path(args.file)
    from daemon.config import load_daemon_config

    cfg = load_daemon_config(args.config)
    if cfg.users_file is None:
        raise UserError(f"{args.config}: hmi.users_file is not set: add e.g. "
                        "'users_file: users' under hmi (relative to the config)")
    return cfg.users_file


def _password(args: argparse.Namespace, name: str) -> str:
    if args.password_stdin:
        line = sys.stdin.readline()
        return line[:-1] if line.endswith("\n") else line
    if not sys.stdin.isatty():
        raise UserError("no terminal to ask the password on: give --password-stdin")
    first = getpass.getpass(f"password for {name}: ")
    if getpass.getpass("again: ") != first:
        raise UserError("the two passwords differ; nothing changed")
    return first


def print_log(args: argparse.Namespace) -> int:
    """The HMI's audit trail, newest first: when, machine, action, person (role, how signed
    in), run, outcome and the pre-flight list."""
    import time

    from daemon.config import load_daemon_config
    from daemon.store.actions import actions
    from daemon.store.journal import Store

    if not args.config:
        raise UserError("rumba users log reads the journal: give --config daemon.yaml")
    if not 1 <= args.limit <= 10_000:
        raise UserError("--limit: 1 to 10000")
    store = Store(load_daemon_config(args.config).store_path)
    try:
        rows = actions(store, args.machine, args.limit)
    finally:
        store.close()
    if not rows:
        print("no HMI actions journaled" + (f" for {args.machine}" if args.machine else ""))
    for a in rows:
        when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(a.at))
        extra = f"  [{a.detail}]" if a.detail else ""
        print(f"{when}  {a.machine:<16} {a.action:<8} {a.person} ({a.role}, {a.via})  "
              f"run {a.run_id or '-'}  {a.outcome}{extra}")
    return 0


def cmd_users(args: argparse.Namespace) -> int:
    if args.action == "log":
        return print_log(args)
    path = users_path(args)
    try:
        users = read_users(path)
        if args.action == "list":
            if not users:
                print(f"{path}: no accounts (add one with rumba users add NAME --role ROLE)")
            for u in users.values():
                print(f"{u.name:<24} {u.role}")
            return 0
        name = check_name(args.name)
        if args.action == "add":
            if name in users:
                raise UserError(f"{path}: user {name!r} exists; use passwd to change it")
            users[name] = User(name, args.role, hash_password(_password(args, name)))
            what = f"added {name} ({args.role})"
        elif args.action == "passwd":
            old = users.get(name)
            if old is None:
                raise UserError(f"{path}: no user {name!r}")
            role = args.role or old.role
            users[name] = User(name, role, hash_password(_password(args, name)))
            what = f"new password for {name} ({role}); their sessions are signed out"
        else:
            if users.pop(name, None) is None:
                raise UserError(f"{path}: no user {name!r}")
            what = f"removed {name}; their sessions are signed out"
        write_users(path, users)
    except UsersError as e:
        raise UserError(str(e)) from None
    except OSError as e:
        raise UserError(f"{path}: cannot write the users file: {e.strerror}") from None
    print(f"{what} — wrote {path}")
    return 0
