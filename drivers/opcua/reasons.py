"""What a failed OPC UA request tells the run: ``why`` words the cause (the connection closed,
no answer in time, the server's status code), and asyncua's client tracebacks about the closed
connection while it reconnects become one DEBUG line each."""

from __future__ import annotations

import logging

from asyncua import ua

_CLOSED = {ua.StatusCodes.BadConnectionClosed, ua.StatusCodes.BadSecureChannelClosed,
           ua.StatusCodes.BadSessionClosed, ua.StatusCodes.BadSessionIdInvalid,
           ua.StatusCodes.BadServerHalted, ua.StatusCodes.BadCommunicationError,
           ua.StatusCodes.BadNotConnected, ua.StatusCodes.BadShutdown}
MISSING_NODE = {ua.StatusCodes.BadNodeIdUnknown, ua.StatusCodes.BadNodeIdInvalid,
                ua.StatusCodes.BadAttributeIdInvalid}
"""A read refused because the node is not there: an address misspelt in the configuration."""


def why(e: BaseException, timeout_s: float | None = None) -> str:
    """What happened to a request, in words that name it: the connection closed, no answer in
    time, the server's status code; never an empty string (a bare ``TimeoutError()`` has
    none)."""
    text = str(e).strip()
    if isinstance(e, TimeoutError):
        within = f" within {timeout_s:g} s" if timeout_s else ""
        return f"no answer from the controller{within}"
    if isinstance(e, ua.UaStatusCodeError):
        name = ua.StatusCode(e.code).name
        if e.code in _CLOSED:
            return f"connection to the controller closed ({name})"
        return name
    if isinstance(e, ConnectionError | OSError):
        return f"connection to the controller closed ({text or type(e).__name__})"
    return f"{type(e).__name__}: {text}" if text else type(e).__name__


class _ConnectionLossNoise(logging.Filter):
    """asyncua's client logs a traceback at ERROR for each background step that meets the
    closed connection while it reconnects ("Publish iteration crashed; retrying in 1s", about
    once a second); the link reports the lost connection itself, in the run's reason. Such a
    record becomes one DEBUG line; any other exception keeps its traceback."""

    def filter(self, record: logging.LogRecord) -> bool:
        exc = record.exc_info[1] if record.exc_info else None
        if exc is not None and (isinstance(exc, ConnectionError | OSError | TimeoutError)
                                or (isinstance(exc, ua.UaStatusCodeError)
                                    and exc.code in _CLOSED)):
            record.msg = f"{record.getMessage()} ({why(exc)})"
            record.args = None
            record.exc_info = record.exc_text = None
            record.levelno, record.levelname = logging.DEBUG, "DEBUG"
        return True


CLIENT_LOGGERS = ("asyncua.client.client", "asyncua.client.ua_client.UASocketProtocol",
                  "asyncua.client.ua_client.UaClient", "asyncua.client.ua_session.UaSession",
                  "asyncua.client.ua_session")
"""asyncua's client loggers that log a step failing on the closed connection."""


def quiet_connection_loss() -> None:
    """Install ``_ConnectionLossNoise`` on asyncua's client loggers (once)."""
    for name in CLIENT_LOGGERS:
        lg = logging.getLogger(name)
        if not any(isinstance(f, _ConnectionLossNoise) for f in lg.filters):
            lg.addFilter(_ConnectionLossNoise())
