"""HMI accounts: a users file with scrypt hashes the admin edits with
`rumba users`, sign-in with name and password, roles (an operator starts and aborts, only an
engineer or admin confirms or rolls back a compensation), every start / abort / confirm /
rollback journaled with the person, the run's "started by" the person, the pre-flight list,
a new password or a removed account ends that person's sessions; the token stays for scripts."""

from __future__ import annotations

import io
import os
import stat
import sys

import aiohttp
import pytest

from benchmarks.rigs.daemon_helpers import thesis_rows, thesis_setup, write_daemon_yaml
from contracts.yaml_files import ConfigError
from daemon.analysis.replay_link import ReplayLink, prepare_from_rows
from daemon.config import load_daemon_config
from daemon.hmi.users import UsersError, parse, read_users, verify_password
from daemon.service.service import Service
from daemon.store.actions import actions
from tests.cli_helpers import run_cli

TOKEN = "t0k3n-for-users-0123456789"
PREFLIGHT = {"preflight": ["probe", "balls", "doors", "area"]}
PASSWORDS = {"olga": "operator-pass-1", "erik": "engineer-pass-2"}


def add_user(capsys, monkeypatch, users, name: str, role: str, password: str) -> str:
    monkeypatch.setattr(sys, "stdin", io.StringIO(password + "\n"))
    code, out, err = run_cli(["users", "--file", str(users), "add", name, "--role", role,
                              "--password-stdin"], capsys)
    assert code == 0, err
    return out


def test_cli_add_passwd_remove_list(tmp_path, capsys, monkeypatch):
    users = tmp_path / "users"
    out = add_user(capsys, monkeypatch, users, "olga", "operator", "operator-pass-1")
    assert out.strip() == f"added olga (operator) — wrote {users}"
    assert stat.S_IMODE(users.stat().st_mode) == 0o600  # hashes are guessable offline
    text = users.read_text()
    assert "operator-pass-1" not in text and "olga:operator:scrypt$16384$8$1$" in text
    add_user(capsys, monkeypatch, users, "erik", "engineer", "engineer-pass-2")
    code, out, _ = run_cli(["users", "--file", str(users), "list"], capsys)
    assert code == 0 and out.split() == ["olga", "operator", "erik", "engineer"]
    # an existing name, a short password, a bad name: one line each, nothing written
    before = users.read_text()
    monkeypatch.setattr(sys, "stdin", io.StringIO("another-pass-3\n"))
    code, _, err = run_cli(["users", "--file", str(users), "add", "olga", "--role", "admin",
                            "--password-stdin"], capsys)
    assert code == 2 and "user 'olga' exists" in err
    monkeypatch.setattr(sys, "stdin", io.StringIO("short\n"))
    code, _, err = run_cli(["users", "--file", str(users), "add", "anna", "--role", "admin",
                            "--password-stdin"], capsys)
    assert code == 2 and "password: 10 to 1024 characters" in err
    monkeypatch.setattr(sys, "stdin", io.StringIO("another-pass-3\n"))
    code, _, err = run_cli(["users", "--file", str(users), "add", "Bad:Name", "--role",
                            "admin", "--password-stdin"], capsys)
    assert code == 2 and "user name 'Bad:Name'" in err
    monkeypatch.setattr(sys, "stdin", io.StringIO("another-pass-3\n"))
    code, _, err = run_cli(["users", "--file", str(users), "add", "token", "--role",
                            "admin", "--password-stdin"], capsys)
    assert code == 2 and "reserved" in err
    assert users.read_text() == before
    # passwd: a new hash (new salt), the role may change; remove
    monkeypatch.setattr(sys, "stdin", io.StringIO("new-operator-pass\n"))
    code, out, _ = run_cli(["users", "--file", str(users), "passwd", "olga", "--role",
                            "engineer", "--password-stdin"], capsys)
    assert code == 0 and "signed out" in out
    olga = read_users(users)["olga"]
    assert olga.role == "engineer" and verify_password("new-operator-pass", olga.hash)
    assert not verify_password("operator-pass-1", olga.hash)
    code, _, _ = run_cli(["users", "--file", str(users), "remove", "olga"], capsys)
    assert code == 0 and list(read_users(users)) == ["erik"]
    code, _, err = run_cli(["users", "--file", str(users), "remove", "olga"], capsys)
    assert code == 2 and "no user 'olga'" in err


def test_users_file_errors_name_the_line(tmp_path):
    with pytest.raises(UsersError, match=r"users:2: expected name:role"):
        parse("# accounts\nolga:operator\n", "users")
    with pytest.raises(UsersError, match=r"users:1: role 'boss'"):
        parse("olga:boss:scrypt$16384$8$1$AAAAAAAAAAAA$AAAAAAAAAAAAAAAAAAAAAA\n", "users")
    with pytest.raises(UsersError, match=r"users:1: the password of 'olga' is not a scrypt"):
        parse("olga:operator:hunter2\n", "users")  # a plain password typed in by hand
    path = tmp_path / "users"
    path.write_text("# none yet\n")
    os.chmod(path, 0o644)
    with pytest.raises(UsersError, match="readable by others"):
        read_users(path)
    cfg = write_daemon_yaml(tmp_path, token=TOKEN)
    cfg.write_text(cfg.read_text().replace(f"token: {TOKEN}}}",
                                           f"token: {TOKEN}, users_file: users}}"))
    with pytest.raises(ConfigError, match=r"daemon.yaml: hmi.users_file: .*chmod 600"):
        load_daemon_config(cfg)


async def accounts_service(tmp_path, capsys, monkeypatch, delay_s: float = 0.0) -> Service:
    users = tmp_path / "users"
    add_user(capsys, monkeypatch, users, "olga", "operator", PASSWORDS["olga"])
    add_user(capsys, monkeypatch, users, "erik", "engineer", PASSWORDS["erik"])
    cfg = write_daemon_yaml(tmp_path, token=TOKEN)
    cfg.write_text(cfg.read_text().replace(f"token: {TOKEN}}}",
                                           f"token: {TOKEN}, users_file: users}}"))
    rows = thesis_rows(thesis_setup())
    svc = Service(load_daemon_config(cfg), lambda s: ReplayLink(rows, s.machine,
                                                                 delay_s=delay_s),
                  prepare=prepare_from_rows(rows))
    await svc.start()
    return svc


def jar_session() -> aiohttp.ClientSession:
    """A client keeping cookies of an IP-address host (aiohttp drops them by default)."""
    return aiohttp.ClientSession(cookie_jar=aiohttp.CookieJar(unsafe=True))


async def sign_in(http: aiohttp.ClientSession, url: str, user: str, password: str
                  ) -> tuple[int, str]:
    """(status of the login, the page's CSRF token or '')."""
    r = await http.post(url + "login", data={"user": user, "password": password},
                        allow_redirects=False)
    if r.status != 303:
        return r.status, ""
    cookie = r.headers["Set-Cookie"]
    assert "HttpOnly" in cookie and "SameSite=Strict" in cookie, cookie
    page = await (await http.get(url)).text()
    return 303, page.split('name="csrf-token" content="')[1].split('"')[0]


async def test_roles_journal_and_sessions(tmp_path, capsys, monkeypatch):
    svc = await accounts_service(tmp_path, capsys, monkeypatch, delay_s=0.05)
    url = svc.hmi_url
    try:
        async with aiohttp.ClientSession() as anon:
            page = await (await anon.get(url + "login")).text()
            assert 'id="user"' in page and 'id="password"' in page and 'id="token"' not in page
            # with accounts the form takes no token: people sign in as themselves
            r = await anon.post(url + "login", data={"token": TOKEN}, allow_redirects=False)
            assert r.status == 401 and "it is for scripts" in await r.text()
            # the token typed into the password (or name) field: said what it is for, with
            # the header to send it in, never echoed, and a cookie is not given
            for field in ("password", "user"):
                form = {"user": "olga", "password": "x", field: TOKEN}
                r = await anon.post(url + "login", data=form, allow_redirects=False)
                text = await r.text()
                assert r.status == 401 and "Set-Cookie" not in r.headers
                assert "the daemon&#x27;s token: it is for scripts" in text or \
                    "the daemon's token: it is for scripts" in text, text
                assert "Authorization: Bearer &lt;token&gt;" in text and TOKEN not in text
                assert "Wrong name or password" not in text
            r = await anon.post(url + "login", data={"user": "olga", "password": TOKEN[:-1]},
                                allow_redirects=False)
            assert r.status == 401 and "Wrong name or password" in await r.text()
            assert (await sign_in(anon, url, "olga", "wrong-password"))[0] == 401
            assert (await sign_in(anon, url, "nobody", PASSWORDS["olga"]))[0] == 401
        async with jar_session() as olga, jar_session() as erik:
            status, csrf_o = await sign_in(olga, url, "olga", PASSWORDS["olga"])
            assert status == 303
            me = await (await olga.get(url + "api/me")).json()
            assert me == {"name": "olga", "role": "operator", "via": "password",
                          "may_compensate": False}
            h_o = {"X-CSRF-Token": csrf_o}
            start = url + "api/machines/mill1/start"
            r = await olga.post(start, headers=h_o)  # Start asks for the pre-flight list
            assert r.status == 400 and "pre-flight checklist not confirmed" in await r.text()
            r = await olga.post(start, headers=h_o, json=PREFLIGHT)
            assert r.status == 202, await r.text()
            run_id = (await r.json())["run_id"]
            r = await olga.post(url + "api/machines/mill1/abort", headers=h_o)
            assert r.status == 200
            assert (await r.json())["reason"].startswith("aborted by olga (hmi)")
            run = svc.store.run(run_id)
            assert run.started_by == "olga" and run.trigger == "hmi"
            listed = (await (await olga.get(url + "api/runs?limit=1")).json())[0]
            assert listed["id"] == run_id and listed["started_by"] == "olga"
            # an operator may not confirm or roll back a compensation
            for what, body in (("confirm", {"machine": "mill1", "run_id": run_id}),
                               ("rollback", {"machine": "mill1"})):
                r = await olga.post(url + f"api/compensation/{what}", headers=h_o, json=body)
                assert r.status == 403, what
                assert "signed in as olga (operator)" in await r.text()
                assert "needs an engineer or admin" in await r.text()
            # an engineer may: the request reaches the compensation (nothing to apply here)
            # and is journaled with the person
            status, csrf_e = await sign_in(erik, url, "erik", PASSWORDS["erik"])
            r = await erik.post(url + "api/compensation/rollback",
                                headers={"X-CSRF-Token": csrf_e}, json={"machine": "mill1"})
            assert r.status == 409, await r.text()
            rows = [(a.action, a.person, a.role, a.via, a.outcome.split(":")[0], a.run_id)
                    for a in reversed(actions(svc.store, "mill1"))]
            assert rows == [("start", "olga", "operator", "password", "ok", run_id),
                            ("abort", "olga", "operator", "password", "ok", run_id),
                            ("confirm", "olga", "operator", "password", "refused", run_id),
                            ("rollback", "olga", "operator", "password", "refused", ""),
                            ("rollback", "erik", "engineer", "password", "refused", "")]
            assert "needs an engineer or admin" in actions(svc.store, "mill1")[1].outcome
            start_row = actions(svc.store, "mill1")[-1]
            assert start_row.detail == "pre-flight ticked: probe, balls, doors, area"
            # the token is for scripts: a bearer start needs no pre-flight list
            async with aiohttp.ClientSession(
                    headers={"Authorization": f"Bearer {TOKEN}"}) as script:
                r = await script.post(start + "?trigger=cli")
                assert r.status == 202
                script_run = (await r.json())["run_id"]
                await svc.sessions["mill1"].wait()
            assert svc.store.run(script_run).started_by == ""
            assert actions(svc.store, "mill1")[0].via == "bearer"
            # the audit trail as the quality engineer reads it
            code, out, _ = run_cli(["users", "--config", str(tmp_path / "daemon.yaml"), "log",
                                    "--machine", "mill1"], capsys)
            lines = out.splitlines()
            assert code == 0 and len(lines) == 6, out
            assert "mill1            start    token (admin, bearer)" in lines[0]
            assert "rollback erik (engineer, password)  run -  refused: " in lines[1]
            assert "rollback olga (operator, password)  run -  refused: signed in as olga " \
                   "(operator): rolling back a compensation needs an engineer or admin" in lines[2]
            assert f"abort    olga (operator, password)  run {run_id}  ok" in lines[4]
            assert lines[5].endswith(f"start    olga (operator, password)  run {run_id}  ok  "
                                     "[pre-flight ticked: probe, balls, doors, area]")
            # a new password ends olga's session; removing erik ends his
            monkeypatch.setattr(sys, "stdin", io.StringIO("a-new-password-9\n"))
            code, _, _ = run_cli(["users", "--file", str(tmp_path / "users"), "passwd", "olga",
                                  "--password-stdin"], capsys)
            assert code == 0
            assert (await olga.get(url + "api/me")).status == 401
            assert (await erik.get(url + "api/me")).status == 200
            code, _, _ = run_cli(["users", "--file", str(tmp_path / "users"), "remove", "erik"],
                                 capsys)
            assert (await erik.get(url + "api/me")).status == 401
    finally:
        await svc.stop()
