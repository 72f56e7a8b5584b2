"""Typed exceptions for everything the esa server (or the connection to it) can report.

Every failure surfaces as an :class:`EsaError` subclass carrying the gRPC status
``code`` and the server's ``message``; :func:`esa_error` is the single place that
maps a ``grpc.RpcError`` or a ``StreamError`` onto these types.
"""

from __future__ import annotations

from typing import Protocol

import grpc


class EsaError(Exception):
    """Base class of all esa client errors.

    Attributes:
        code: The gRPC status code the server (or the transport) reported.
        message: The human-readable message, naming what to fix.
    """

    def __init__(self, message: str, code: grpc.StatusCode = grpc.StatusCode.UNKNOWN) -> None:
        """Creates the error from the server's message and status code."""
        super().__init__(f"{message} [{code.name}]")
        self.code = code
        self.message = message


class SessionNotFound(EsaError, LookupError):
    """The session id is unknown, closed or expired (``NOT_FOUND``)."""


class InvalidArgument(EsaError, ValueError):
    """The request was malformed: bad config, wrong length, NaN, ... (``INVALID_ARGUMENT``)."""


class StepMismatch(EsaError):
    """The step does not match the session, or a report had no probe (``FAILED_PRECONDITION``)."""


class ResourceExhausted(EsaError):
    """A server limit is reached (``RESOURCE_EXHAUSTED``).

    The message names the limit: live sessions (``--max-sessions``), session memory
    (``--max-session-memory``), the size of one request (``--max-message-bytes``) or the
    request memory of all calls in flight (``--max-request-memory``).
    """


class Unauthenticated(EsaError, PermissionError):
    """The server requires an auth token and none, or another one, was sent (``UNAUTHENTICATED``).

    Give the client the server's token: ``EsaClient(..., token=...)``, ``token_file=...`` or
    the ``ESA_AUTH_TOKEN`` environment variable.
    """


class SessionAlreadyExists(EsaError):
    """The session id exists with a different config (``ALREADY_EXISTS``)."""


class ServerUnavailable(EsaError, ConnectionError):
    """The server cannot be reached or the connection was lost (``UNAVAILABLE``)."""


class DeadlineExceeded(EsaError, TimeoutError):
    """The server did not answer within the call's deadline (``DEADLINE_EXCEEDED``)."""


_BY_CODE: dict[grpc.StatusCode, type[EsaError]] = {
    grpc.StatusCode.NOT_FOUND: SessionNotFound,
    grpc.StatusCode.INVALID_ARGUMENT: InvalidArgument,
    grpc.StatusCode.FAILED_PRECONDITION: StepMismatch,
    grpc.StatusCode.RESOURCE_EXHAUSTED: ResourceExhausted,
    grpc.StatusCode.ALREADY_EXISTS: SessionAlreadyExists,
    grpc.StatusCode.UNAUTHENTICATED: Unauthenticated,
    grpc.StatusCode.UNAVAILABLE: ServerUnavailable,
    grpc.StatusCode.DEADLINE_EXCEEDED: DeadlineExceeded,
}
_BY_NUMBER: dict[int, grpc.StatusCode] = {code.value[0]: code for code in grpc.StatusCode}


class StreamErrorLike(Protocol):
    """Anything shaped like the ``esa.v1.StreamError`` message."""

    code: int
    message: str


def esa_error(source: grpc.RpcError | StreamErrorLike) -> EsaError:
    """Maps a failed gRPC call or a ``StreamError`` to the matching :class:`EsaError` subclass.

    Args:
        source: A ``grpc.RpcError`` raised by a call (it also implements ``grpc.Call``),
            or a ``StreamError`` message (gRPC code number plus message).

    Returns:
        The typed exception, ready to raise; unknown codes give a plain :class:`EsaError`.
    """
    if isinstance(source, grpc.RpcError):
        code = source.code() if hasattr(source, "code") else grpc.StatusCode.UNKNOWN
        message = source.details() if hasattr(source, "details") else str(source)
    else:
        code = _BY_NUMBER.get(source.code, grpc.StatusCode.UNKNOWN)
        message = source.message
    return _BY_CODE.get(code, EsaError)(message or code.name.lower(), code)
