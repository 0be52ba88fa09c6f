"""An asyncua client set up from a link section: its security (Basic256Sha256) and its user."""

from __future__ import annotations

from typing import Any

from asyncua import Client, ua
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256


async def secure_client(cfg: Any) -> Client:
    """A client for ``cfg.url`` (not yet connected) with the section's security mode,
    certificates and user; the same for the gateway profile and the SINUMERIK one. A
    certificate that cannot be read or a key that does not fit raises OSError / ValueError,
    which the caller words as its own configuration error."""
    client = Client(cfg.url, timeout=cfg.request_timeout_s, watchdog_intervall=2.0)
    client.application_uri = cfg.application_uri
    client.name = "rumba-cnc daemon"
    if cfg.security != "none":
        mode = (ua.MessageSecurityMode.SignAndEncrypt if cfg.security.endswith("Encrypt")
                else ua.MessageSecurityMode.Sign)
        await client.set_security(
            SecurityPolicyBasic256Sha256, certificate=str(cfg.certificate),
            private_key=str(cfg.private_key),
            server_certificate=str(cfg.server_certificate) if cfg.server_certificate else None,
            mode=mode)
    if cfg.user is not None:
        client.set_user(cfg.user.name)
        client.set_password(cfg.user.secret())
    return client
