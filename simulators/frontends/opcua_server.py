"""An asyncua server as a simulated controller publishes it: one security policy (Basic256Sha256
SignAndEncrypt by default, a certificate generated on first start), user/password checked by a
user manager, anonymous only when ``security="none"`` is asked for (tests), client certificates
checked against a trust folder when one is given. asyncua's defaults (every policy, every user)
are never used. Shared by the rumba gateway front-end and the SINUMERIK profile's."""

from __future__ import annotations

import socket
from pathlib import Path

from asyncua import Server, ua
from asyncua.crypto.truststore import TrustStore
from asyncua.crypto.validator import CertificateValidator, CertificateValidatorOptions

from contracts.opcua_certs import ensure_certificate
from contracts.opcua_security import PasswordUsers, SecureServer

POLICIES = {
    "Basic256Sha256_SignAndEncrypt": ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt,
    "Basic256Sha256_Sign": ua.SecurityPolicyType.Basic256Sha256_Sign,
    "none": ua.SecurityPolicyType.NoSecurity,
}


def check_security(security: str, cert_dir: Path | None, users: dict[str, str] | None) -> None:
    """ValueError unless the security settings make a server rumba would ship."""
    if security not in POLICIES:
        raise ValueError(f"security {security!r}: expected one of {sorted(POLICIES)}")
    if security != "none" and cert_dir is None:
        raise ValueError(f"security {security} needs a certificate folder (cert_dir)")
    if security != "none" and not users:
        raise ValueError(f"security {security} needs users (user/password authentication)")


async def secure_server(*, security: str, cert_dir: Path | None, users: dict[str, str] | None,
                        trusted: list[Path] | None, application_uri: str, name: str,
                        endpoint: str) -> tuple[Server, Path | None]:
    """The initialised server (not listening) and its certificate's path (None without
    security)."""
    check_security(security, cert_dir, users)
    cls = Server if security == "none" else SecureServer
    server = cls(user_manager=PasswordUsers(users or None))
    await server.init()
    server.set_endpoint(endpoint)
    server.set_server_name(name)
    await server.set_application_uri(application_uri)
    server.set_security_policy([POLICIES[security]])
    server.set_identity_tokens([ua.UserNameIdentityToken] if users
                               else [ua.AnonymousIdentityToken])
    if security == "none":
        return server, None
    assert cert_dir is not None
    cert, key = cert_dir / "server_cert.der", cert_dir / "server_key.pem"
    await ensure_certificate(cert, key, application_uri, server=True)
    await server.load_certificate(str(cert))
    await server.load_private_key(str(key))
    if trusted is not None:
        store = TrustStore(list(trusted), [])
        await store.load()
        validator = CertificateValidator(
            CertificateValidatorOptions.TRUSTED_VALIDATION
            | CertificateValidatorOptions.PEER_CLIENT, store)
    else:
        validator = CertificateValidator(CertificateValidatorOptions.EXT_VALIDATION
                                         | CertificateValidatorOptions.PEER_CLIENT)
    server.set_certificate_validator(validator)
    return server, cert


def free_port(host: str) -> int:
    """A free port for the endpoint URL (the URL must name the port clients will use)."""
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]
