"""OPC UA server security shared by the simulator's controller server and the daemon's results
server: user/password authentication (constant time) and an asyncua server that refuses every
service but discovery on an unsecured channel. asyncua's defaults (every policy, every user) are
never used."""

from __future__ import annotations

import hmac
from contextvars import ContextVar
from typing import Any

from asyncua import Server, ua
from asyncua.common.utils import ServiceError
from asyncua.crypto.permission_rules import User, UserRole
from asyncua.crypto.security_policies import SecurityPolicyNone
from asyncua.server.binary_server_asyncio import BinaryServer
from asyncua.server.user_managers import UserManager


class PasswordUsers(UserManager):
    """User/password check (constant-time); ``users=None`` admits anonymous sessions."""

    def __init__(self, users: dict[str, str] | None) -> None:
        self.users = users

    def get_user(self, iserver: Any, username: str | None = None, password: Any = None,
                 certificate: Any = None) -> User | None:
        if self.users is None:
            return User(role=UserRole.User)
        if username is None or username not in self.users:
            return None
        given = password.encode() if isinstance(password, str) else bytes(password or b"")
        if hmac.compare_digest(given, self.users[username].encode()):
            return User(role=UserRole.User, name=username)
        return None


CHANNEL: ContextVar[Any] = ContextVar("rumba_opcua_channel", default=None)
"""The connection whose request is being served (asyncua's ``UaProcessor``: the peer address
``name``, its ``session``), for a user manager or a method that needs to know who asks."""

DISCOVERY = (ua.NodeId(ua.ObjectIds.GetEndpointsRequest_Encoding_DefaultBinary),
             ua.NodeId(ua.ObjectIds.FindServersRequest_Encoding_DefaultBinary))


class SecureOnlyBinaryServer(BinaryServer):
    """Refuses every service but discovery on an unsecured channel.

    asyncua's server (2.1) lets a client open a None channel and then create and activate a
    session on it even when only Basic256Sha256 endpoints are published - with the password in
    plain text. OPC UA allows None only for GetEndpoints/FindServers; enforce that here."""

    def _make_protocol(self) -> Any:
        proto = super()._make_protocol()
        made = proto.connection_made

        def connection_made(transport: Any) -> None:
            made(transport)
            if proto.processor is not None:
                _guard(proto.processor)
        proto.connection_made = connection_made
        return proto


def _guard(processor: Any) -> None:
    inner = processor._process_message

    async def process(typeid: Any, requesthdr: Any, seqhdr: Any, body: Any) -> Any:
        if (processor._connection.security_policy.URI == SecurityPolicyNone.URI
                and typeid not in DISCOVERY):
            raise ServiceError(ua.StatusCodes.BadSecurityModeRejected)
        CHANNEL.set(processor)
        return await inner(typeid, requesthdr, seqhdr, body)
    processor._process_message = process


class SecureServer(Server):
    async def start(self) -> None:
        # Server.start with the guarded binary server (same steps as asyncua 2.1).
        await self._setup_server_nodes()
        await self.iserver.start()
        try:
            host, port = self._get_bind_socket_info()
            self.bserver = SecureOnlyBinaryServer(self.iserver, host, port, self.limits)
            self.bserver.set_policies(self._policies)
            await self.bserver.start()
        except Exception:
            await self.iserver.stop()
            raise
