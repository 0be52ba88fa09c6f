"""The HMI's TLS server context (TLS ≥ 1.2) from ``hmi.tls`` {cert, key} PEM files, with one
clear line per failure: missing or unreadable file, no certificate, no key, encrypted key, key
not matching the certificate, key readable by everyone."""

from __future__ import annotations

import ssl
import stat
from pathlib import Path

from contracts.yaml_files import ConfigError


class _Encrypted(Exception):
    """OpenSSL asked for a passphrase (it would prompt on a terminal, hang a service)."""


def _refuse_passphrase() -> bytes:
    raise _Encrypted


def server_context(cert: Path, key: Path, where: str) -> ssl.SSLContext:
    """A server context for ``cert`` + ``key``; ``where`` prefixes errors, e.g.
    ``/etc/rumba/daemon.yaml: hmi.tls``. Raises ``ConfigError`` (one line, names the key)."""
    for name, p in (("cert", cert), ("key", key)):
        try:
            mode = stat.S_IMODE(p.stat().st_mode)
            p.open("rb").close()
        except FileNotFoundError:
            raise ConfigError(f"{where}.{name}: file {p} not found") from None
        except OSError as e:
            raise ConfigError(f"{where}.{name}: cannot read {p}: {e.strerror}") from None
        # The group may read a key (Debian's ssl-cert group convention), everyone may not.
        if name == "key" and mode & 0o007:
            raise ConfigError(f"{where}.key: private key {p} is readable by everyone "
                              f"(mode {mode:04o}); chmod 600 (or 640) it")
    probe = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    try:
        probe.load_verify_locations(cafile=str(cert))
    except ssl.SSLError:
        raise ConfigError(f"{where}.cert: {cert} holds no PEM certificate "
                          "(expected '-----BEGIN CERTIFICATE-----')") from None
    ctx = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    # Python ≥ 3.10 defaults to 1.2 already; set it so no OpenSSL policy file lowers it.
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    try:
        ctx.load_cert_chain(str(cert), str(key), password=_refuse_passphrase)
    except _Encrypted:
        raise ConfigError(f"{where}.key: {key} is encrypted with a passphrase; the daemon starts "
                          "unattended: give it an unencrypted key protected by chmod 600 "
                          "(openssl pkey -in KEY -out KEY.plain)") from None
    except ssl.SSLError as e:
        if e.reason == "KEY_VALUES_MISMATCH":
            raise ConfigError(f"{where}.key: private key {key} does not match the certificate "
                              f"{cert}") from None
        raise ConfigError(f"{where}.key: {key} holds no usable PEM private key "
                          f"(expected '-----BEGIN PRIVATE KEY-----'): {e.reason or e}") from None
    except OSError as e:
        raise ConfigError(f"{where}: cannot load {cert} / {key}: {e}") from None
    return ctx
