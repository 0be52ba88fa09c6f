"""Run the `rumba` CLI in-process and capture its output; pick a free loopback port."""

from __future__ import annotations

import socket

from daemon.cli.main import main as cli_main


def run_cli(argv: list[str], capsys) -> tuple[int, str, str]:
    code = cli_main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
