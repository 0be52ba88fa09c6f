"""The HMI over HTTPS with a real self-signed certificate on a free loopback port: a client that
trusts it signs in (Secure cookie), plain HTTP and untrusting or TLS 1.1 clients are refused by
the handshake; bad TLS files are one config line naming the key; a remote HMI without TLS warns."""

from __future__ import annotations

import asyncio
import logging
import re
import ssl
import warnings
from pathlib import Path

import aiohttp
import pytest

from benchmarks.rigs.daemon_helpers import thesis_rows, thesis_setup, write_daemon_yaml
from daemon.analysis.replay_link import ReplayLink, prepare_from_rows
from daemon.cli.main import main as cli_main
from daemon.config import load_daemon_config
from daemon.hmi.tls import server_context
from daemon.service.service import Service, ServiceError
from tests.tls_helpers import make_cert

TOKEN = "t0k3n-for-tests-0123456789"


def tls_yaml(tmp_path: Path, cert: Path, key: Path, host: str = "127.0.0.1") -> Path:
    path = write_daemon_yaml(tmp_path, token=TOKEN)
    text = path.read_text().replace(
        "hmi: {host: 127.0.0.1, port: 0,",
        f"hmi: {{host: '{host}', port: 0, allow_remote: true, "
        f"tls: {{cert: {cert}, key: {key}}},")
    assert "tls:" in text
    path.write_text(text)
    return path


def replay_service(path: Path) -> Service:
    setup = thesis_setup()
    rows = thesis_rows(setup)
    return Service(load_daemon_config(path), lambda s: ReplayLink(rows, s.machine, delay_s=0.01),
                   prepare=prepare_from_rows(rows))


@pytest.fixture
def cert(tmp_path):
    return make_cert(tmp_path)


@pytest.fixture
async def tls_service(tmp_path, cert):
    svc = replay_service(tls_yaml(tmp_path, *cert))
    await svc.start()
    yield svc
    await svc.stop()


def trusting(cert: Path) -> ssl.SSLContext:
    return ssl.create_default_context(cafile=str(cert))


async def test_https_login_status_and_secure_cookie(tls_service, cert):
    url = tls_service.hmi_url
    assert url.startswith("https://127.0.0.1:")
    ctx = trusting(cert[0])
    jar = aiohttp.CookieJar(unsafe=True)  # cookies for an IP address host
    async with aiohttp.ClientSession(cookie_jar=jar) as http:
        r = await http.get(url + "api/status", ssl=ctx)
        assert r.status == 401
        r = await http.post(url + "login", data={"token": TOKEN}, ssl=ctx, allow_redirects=False)
        assert r.status == 303
        cookie = r.headers["Set-Cookie"]
        attrs = {a.strip().split("=")[0].lower() for a in cookie.split(";")[1:]}
        assert {"secure", "httponly"} <= attrs and "SameSite=Strict" in cookie, cookie
        r = await http.get(url + "api/status", ssl=ctx)  # the cookie alone signs in
        assert r.status == 200 and (await r.json())["mill1"]["state"] == "IDLE"
    # The handshake really negotiated TLS ≥ 1.2 with this certificate.
    port = int(url.rsplit(":", 1)[1].strip("/"))
    _, writer = await asyncio.open_connection("127.0.0.1", port, ssl=ctx)
    try:
        assert writer.get_extra_info("ssl_object").version() in ("TLSv1.2", "TLSv1.3")
    finally:
        writer.close()


async def test_plain_http_on_the_tls_port_fails(tls_service):
    plain = tls_service.hmi_url.replace("https://", "http://")
    async with aiohttp.ClientSession() as http:
        with pytest.raises(aiohttp.ClientError):
            r = await http.get(plain + "login")
            await r.read()  # no HTTP answer may come back in clear text


async def test_client_not_trusting_the_cert_is_refused(tls_service):
    async with aiohttp.ClientSession() as http:  # system CAs only: the self-signed cert fails
        with pytest.raises(aiohttp.ClientConnectorCertificateError):
            await http.get(tls_service.hmi_url + "login")


async def test_tls_below_1_2_is_refused(tls_service, cert):
    assert server_context(*cert, "hmi.tls").minimum_version == ssl.TLSVersion.TLSv1_2
    old = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    old.load_verify_locations(cafile=str(cert[0]))
    # This client can speak TLS 1.1 (checked by hand against a server allowing it); the HMI
    # must end the handshake.
    old.set_ciphers("DEFAULT:@SECLEVEL=0")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        old.minimum_version = ssl.TLSVersion.TLSv1
        old.maximum_version = ssl.TLSVersion.TLSv1_1
    port = int(tls_service.hmi_url.rsplit(":", 1)[1].strip("/"))
    with pytest.raises((ssl.SSLError, ConnectionResetError)):
        await asyncio.open_connection("127.0.0.1", port, ssl=old)


# ------------------------------------------------------------------------ configuration errors


def _other_cert_key(tmp_path: Path, cert: tuple[Path, Path]) -> tuple[Path, Path]:
    return cert[0], make_cert(tmp_path, "other")[1]


def _missing_key(tmp_path: Path, cert: tuple[Path, Path]) -> tuple[Path, Path]:
    return cert[0], tmp_path / "gone.key"


def _encrypted_key(tmp_path: Path, cert: tuple[Path, Path]) -> tuple[Path, Path]:
    return make_cert(tmp_path, "enc", passphrase=b"secret-pass")


def _world_readable_key(tmp_path: Path, cert: tuple[Path, Path]) -> tuple[Path, Path]:
    cert[1].chmod(0o644)
    return cert


def _cert_as_key(tmp_path: Path, cert: tuple[Path, Path]) -> tuple[Path, Path]:
    wrong = tmp_path / "cert-copy.key"
    wrong.touch(mode=0o600)
    wrong.write_bytes(cert[0].read_bytes())
    return cert[0], wrong


def _key_as_cert(tmp_path: Path, cert: tuple[Path, Path]) -> tuple[Path, Path]:
    return cert[1], cert[1]


@pytest.mark.parametrize(("files", "expect"), [
    (_other_cert_key, r"hmi\.tls\.key: private key .*other\.key does not match the certificate "
                      r".*hmi\.crt$"),
    (_missing_key, r"hmi\.tls\.key: file .*gone\.key not found$"),
    (_encrypted_key, r"hmi\.tls\.key: .*enc\.key is encrypted with a passphrase"),
    (_world_readable_key, r"hmi\.tls\.key: private key .*hmi\.key is readable by everyone "
                          r"\(mode 0644\)"),
    (_cert_as_key, r"hmi\.tls\.key: .*cert-copy\.key holds no usable PEM private key"),
    (_key_as_cert, r"hmi\.tls\.cert: .*hmi\.key holds no PEM certificate"),
])
def test_bad_tls_files_are_one_config_line(tmp_path, capsys, cert, files, expect):
    path = tls_yaml(tmp_path, *files(tmp_path, cert))
    code = cli_main(["run", "--config", str(path), "--check"])
    out, err = capsys.readouterr()
    assert code == 2 and out == ""
    assert err.count("\n") == 1 and err.startswith(f"error: {path}: hmi.tls."), err
    assert re.search(expect, err.strip()), err


def test_good_tls_files_pass_the_check(tmp_path, capsys, cert):
    path = tls_yaml(tmp_path, *cert)
    assert cli_main(["run", "--config", str(path), "--check"]) == 0
    assert "OK (1 machines: mill1)" in capsys.readouterr().out


# ------------------------------------------------------------------- remote HMI without TLS

# TEST-NET-1 (RFC 5737): never assigned to this host, so the bind fails after the warning and
# nothing is ever exposed on a real interface.
REMOTE = "192.0.2.1"


async def test_remote_hmi_without_tls_warns_loudly(tmp_path, caplog):
    path = write_daemon_yaml(tmp_path, token=TOKEN)
    path.write_text(path.read_text().replace("hmi: {host: 127.0.0.1,",
                                             f"hmi: {{host: '{REMOTE}', allow_remote: true,"))
    svc = replay_service(path)
    with caplog.at_level(logging.WARNING, "rumba.service"), pytest.raises(ServiceError):
        await svc.start()
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any(f"listening on {REMOTE} without tls" in m and "configure hmi.tls" in m
               for m in warned), warned


async def test_remote_hmi_with_tls_does_not_warn(tmp_path, caplog, cert):
    svc = replay_service(tls_yaml(tmp_path, *cert, host=REMOTE))
    with caplog.at_level(logging.WARNING, "rumba.service"), pytest.raises(ServiceError):
        await svc.start()
    assert not [r for r in caplog.records if "without tls" in r.getMessage()]
