"""``rumba fleet`` and its PostgreSQL: a store that is down at the start is one ``error:`` line
naming it, exit 2, instead of a page that silently answers 503; an outage while it serves is
one line on the terminal when it begins and one when the store is back."""

from __future__ import annotations

import asyncio
import sys

import aiohttp
import pytest

from daemon.cli.main import main
from tests.cli_helpers import free_port
from tests.fleet_helpers import fresh_db, start_postgres, until
from tests.stop_helpers import ROOT

pytestmark = [pytest.mark.peer]
TOKEN = "fleet-t0k3n-0123456789"


def _token(tmp_path):
    token = tmp_path / "token"
    token.write_text(TOKEN)
    token.chmod(0o600)
    return token


def test_a_store_that_is_down_at_the_start_is_one_error_line(tmp_path, capsys):
    dsn = f"postgresql://rumba@127.0.0.1:{free_port()}/fleet"  # nothing listens there
    code = main(["fleet", "--store", dsn, "--token-file", str(_token(tmp_path)),
                 "--listen", "127.0.0.1:0"])
    out, err = capsys.readouterr()
    assert code == 2, (out, err)
    assert err.startswith(f"error: --store: fleet store {dsn}: ") and err.count("\n") == 1, err
    assert "is PostgreSQL running and reachable?" in err and "Traceback" not in err
    assert "rumba fleet: http" not in out  # no page was served


async def test_an_outage_while_serving_is_said_when_it_begins_and_ends(tmp_path):
    pg = start_postgres()
    proc = None
    err = tmp_path / "stderr.txt"  # the terminal: what rumba fleet said, line by line
    try:
        dsn = fresh_db(pg)
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "daemon.cli", "fleet", "--store", dsn, "--token-file",
            str(_token(tmp_path)), "--listen", "127.0.0.1:0", cwd=ROOT,
            stdout=asyncio.subprocess.PIPE, stderr=err.open("w"))
        assert proc.stdout is not None
        line = (await asyncio.wait_for(proc.stdout.readline(), 60)).decode()
        assert line.startswith("rumba fleet: http://127.0.0.1:"), line
        url = line.split(": ", 1)[1].strip()
        async with aiohttp.ClientSession(headers={"Authorization": f"Bearer {TOKEN}"}) as h:
            async with h.get(url + "api/fleet") as r:
                assert r.status == 200
            pg.stop("fast")
            for _ in range(3):  # said once, however many requests meet the outage
                async with h.get(url + "api/fleet") as r:
                    assert r.status == 503
            await until(lambda: err.read_text().count("\n") >= 1, what="the outage said")
            said = err.read_text()
            assert said.startswith("error: rumba.fleet: fleet store ") and said.count("\n") == 1 \
                and "unreachable" in said and "answers 503 until it is back" in said, said
            pg.start()
            async with h.get(url + "api/fleet") as r:
                assert r.status == 200
            await until(lambda: err.read_text().count("\n") >= 2, what="the return said")
            back = err.read_text().splitlines()[1]
            assert back.startswith("warning: rumba.fleet: fleet store ") and \
                "reachable again after" in back, back
    finally:
        if proc is not None and proc.returncode is None:
            proc.terminate()
            await asyncio.wait_for(proc.wait(), 30)
        pg.close()
