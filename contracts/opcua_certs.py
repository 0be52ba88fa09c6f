"""Self-signed OPC UA application certificates (RSA 2048, SHA-256, DER) for the daemon and the
simulator: OPC 10000-6 §6.2.2 fields (application URI in the SAN, key and extended key usage)."""

from __future__ import annotations

import socket
from pathlib import Path

from asyncua.crypto.cert_gen import setup_self_signed_certificate
from cryptography.x509.oid import ExtendedKeyUsageOID


async def ensure_certificate(cert_path: Path, key_path: Path, application_uri: str, *,
                             server: bool) -> None:
    """Create (or renew when invalid/expired) a certificate + private key pair at these paths.

    The key is written with mode 0600: it authenticates this application to the controller."""
    cert_path.parent.mkdir(parents=True, exist_ok=True)
    key_path.parent.mkdir(parents=True, exist_ok=True)
    use = [ExtendedKeyUsageOID.SERVER_AUTH] if server else [ExtendedKeyUsageOID.CLIENT_AUTH]
    await setup_self_signed_certificate(
        key_path, cert_path, application_uri, socket.gethostname(), use,
        {"organizationName": "rumba-cnc"},
    )
    key_path.chmod(0o600)
