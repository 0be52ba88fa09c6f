"""Property-based fuzzing of the input surfaces that come over a network: an MQTT
password without TLS, the fleet page's paths and the garbage a fleet store may hold (the
command-line and file ones: tests/test_inputs_fuzz_surfaces.py). Classified and counted as in
tests/test_inputs_fuzz.py (``benchmarks.rigs.input_fuzz_helpers``);
``benchmarks/fuzz/inputs.py`` runs the same tests longer."""

from __future__ import annotations

import asyncio
import contextlib
import json
import re
import socket
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import yaml
from hypothesis import example, given
from hypothesis import strategies as st

from benchmarks.rigs.input_fuzz_helpers import Tally, outcome
from contracts.yaml_files import ConfigError
from tests.test_inputs_fuzz import FUZZ

# ---------------------------------------------------------------------- MQTT credentials

_LOOPBACK = ["127.0.0.1", "127.0.0.53", "127.255.255.254", "::1", "localhost"]
_AMBIGUOUS = ["LOCALHOST", "localhost.", "127.1", "0x7f000001", "::ffff:127.0.0.1",
              "0:0:0:0:0:0:0:1", "2130706433", "0177.0.0.1"]
_REMOTE = ["192.0.2.1", "broker.example", "10.0.0.1", "0.0.0.0", "::", "fe80::1",
           "localhost.example", "127.0.0.1.nip.io", "local host", "localhost\x00", "[::1]",
           "1.2.3.4 ", "xn--lcalhost-8ya", "lоcalhost"]


def test_an_mqtt_password_crosses_a_network_only_inside_tls(tmp_path: Path) -> None:
    from benchmarks.rigs.daemon_helpers import write_daemon_yaml
    from daemon.config import load_daemon_config

    tally = Tally("mqtt password / TLS")
    secret = tmp_path / "mqtt.pw"
    secret.write_text("pw-0123456789abcdef")
    secret.chmod(0o600)

    @FUZZ
    @given(host=st.one_of(st.sampled_from(_LOOPBACK + _AMBIGUOUS + _REMOTE),
                          st.text(max_size=20)), tls=st.booleans(), password=st.booleans())
    def run(host: str, tls: bool, password: bool) -> None:
        section = {"host": host, "site": "plant1"}
        if password:
            section |= {"username": "rumba", "password_file": str(secret)}
        if tls:
            section["tls"] = {}
        path = write_daemon_yaml(tmp_path, extra_top=yaml.safe_dump({"mqtt": section}))
        if password and not tls:
            valid = True if host in _LOOPBACK else (None if host in _AMBIGUOUS else False)
        else:
            valid = None  # other rules (host syntax) may refuse it
        tally.add(outcome(lambda: load_daemon_config(path), path, valid),
                  (host, tls, password))

    run()
    tally.verdict()


# ---------------------------------------------------------------------------- fleet page


@contextlib.contextmanager
def _fleet_page(token: str) -> Iterator[tuple[int, asyncio.AbstractEventLoop]]:
    """The real fleet page on a free loopback port, its store a closed loopback port (every
    read is 'unreachable'), in an event loop of its own thread."""
    from aiohttp import web

    from daemon.fleet.app import create_fleet_app

    with socket.socket() as s:  # a port nobody listens on: the store refuses at once
        s.bind(("127.0.0.1", 0))
        dead = s.getsockname()[1]
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    app = create_fleet_app(f"postgresql://rumba@127.0.0.1:{dead}/fleet", token,
                           bind_host="127.0.0.1")
    runner = web.AppRunner(app, handle_signals=False)

    async def start() -> int:
        await runner.setup()
        site = web.TCPSite(runner, "127.0.0.1", 0)
        await site.start()
        return int(runner.addresses[0][1])

    port = asyncio.run_coroutine_threadsafe(start(), loop).result(30)
    try:
        yield port, loop
    finally:
        asyncio.run_coroutine_threadsafe(runner.cleanup(), loop).result(30)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(10)
        loop.close()


_SEGMENT = st.one_of(st.sampled_from(["mill-a", "%00", "mill-a%00", "a%0Ab", "%E2%80%AE",
                                      "x" * 33, "x" * 32, "..", ".", "%2e%2e", "a%2Fb",
                                      "%ff", "mill%20a", "ｍill", "mill.a", "-", "_"]),
                     st.text(st.characters(codec="ascii", exclude_characters="/?#"),
                             min_size=1, max_size=40).map(
                         lambda t: "".join(c if c.isalnum() or c in "-._~" else
                                           f"%{ord(c):02X}" for c in t)))


def test_fleet_page_paths_answer_404_or_the_store_state_never_500() -> None:
    import urllib.error
    import urllib.request
    from urllib.parse import quote, unquote

    token = "t0k3n-for-the-fleet-fuzz-0123"
    tally = Tally("fleet page paths")
    opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))  # loopback, direct
    with _fleet_page(token) as (port, _):

        @FUZZ
        @given(segment=_SEGMENT)
        def run(segment: str) -> None:
            url = f"http://127.0.0.1:{port}/machines/{quote(segment, safe='%-._~')}"
            req = urllib.request.Request(url, headers={"Authorization": f"Bearer {token}"})

            def call() -> int:
                try:
                    with opener.open(req, timeout=8) as r:
                        return int(r.status)
                except urllib.error.HTTPError as e:
                    if e.code == 404:
                        raise ConfigError(f"{url}: 404") from None
                    return int(e.code)

            name = unquote(segment, errors="replace")  # invalid UTF-8: U+FFFD, unsafe
            safe = bool(re.fullmatch(r"[A-Za-z0-9_.-]{1,32}", name, re.ASCII)) and \
                name.strip(".") != ""
            # a safe name reaches the (unreachable) store: 503; anything else is 404
            tally.add(outcome(call, url, safe, lambda s: s == 503),
                      segment)

        run()
    tally.verdict()


_JSON = st.recursive(
    st.one_of(st.none(), st.booleans(), st.floats(allow_nan=True, allow_infinity=True),
              st.integers(-10**20, 10**20), st.integers(-10**400, 10**400),
              st.sampled_from([3.9e16, -3.9e16, 1.7e308, -1.7e308, 1e12, 32503680001.0, -1e11]),
              st.text(max_size=8)),
    lambda inner: st.one_of(st.lists(inner, max_size=4),
                            st.dictionaries(st.sampled_from(["value", "unit", "warn", "fail",
                                                             "links", "default_um",
                                                             "default_urad", "EX0C", "EB0Z",
                                                             "x"]), inner, max_size=4)),
    max_leaves=12)


def test_garbage_in_the_fleet_store_never_costs_the_page() -> None:
    from daemon.fleet import view

    tally = Tally("fleet stored garbage")

    @FUZZ
    @given(limits=_JSON, links=_JSON, started=_JSON, unit=st.sampled_from(["um", "urad", "x"]),
           value=_JSON)
    # found by the longer run (benchmarks/fuzz/inputs.py): a time and a value of 1e16 made
    # the chart's y range zero (ZeroDivisionError), an integer beyond a float overflowed
    @example(limits={}, links={}, started=3.883284668996908e16, unit="um",
             value=3.883284668996908e16)
    @example(limits={"default_um": {"warn": 10**400, "fail": -1.7e308}}, links={},
             started=-1e11, unit="um", value=10**400)
    @example(limits={"default_urad": {"warn": 1.7e308}}, links={}, started=1.7e9, unit="urad",
             value=-1.7e308)
    def run(limits: Any, links: Any, started: Any, unit: str, value: Any) -> None:
        trend = [{"run_id": "r1", "started_at": started, "verdict": "PASS", "links": links},
                 {"run_id": "r2", "started_at": 1.7e9, "verdict": "WARN",
                  "links": {"EX0C": {"value": value, "unit": unit}}}]
        runs = [{"id": "r1", "started_at": started if isinstance(started, float) else 1.7e9,
                 "trigger": "cli", "state": "DONE", "verdict": "PASS", "summary": "<b>",
                 "has_report": True}]

        def call() -> str:
            return view.machine_page("mill-x", {"limits": limits}, runs, trend, 90)

        def check(page: str) -> bool:  # a page, the garbage never as markup, no NaN drawn
            return (page.startswith("<!") and "<b>" not in page
                    and not re.search(r"(?<![\w])-?(nan|inf)(?![\w])", page, re.I))

        tally.add(outcome(call, "store", True, check),
                  json.dumps([limits, links, started, value], default=str)[:300])

    run()
    tally.verdict()
