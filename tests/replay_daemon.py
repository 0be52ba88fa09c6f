"""`python -m tests.replay_daemon daemon.yaml DELAY_S`: the real service (`rumba run` code path)
with the test-only ReplayLink, for subprocess tests (kill -9) until the simulator front-ends
and dialects are wired. The CNC's start request is raised at startup, as a controller keeps it
raised until it gets a verdict."""

from __future__ import annotations

import asyncio
import sys

from benchmarks.rigs.daemon_helpers import thesis_rows
from contracts.yaml_files import ConfigError
from daemon.analysis.replay_link import ReplayLink, prepare_from_rows
from daemon.cli.commands.run import serve
from daemon.cli.main import UserError
from daemon.config import load_daemon_config
from daemon.service.service import Service


def main() -> None:
    cfg = load_daemon_config(sys.argv[1])
    delay = float(sys.argv[2])
    setup = next(iter(cfg.machines.values()))
    rows = thesis_rows(setup)

    def factory(s):
        link = ReplayLink(rows, s.machine, delay_s=delay)
        link.request.set()
        return link

    asyncio.run(serve(Service(cfg, factory, prepare=prepare_from_rows(rows))))


if __name__ == "__main__":
    try:
        main()
    except (UserError, ConfigError) as e:  # as daemon.cli.main does for `rumba run`
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
