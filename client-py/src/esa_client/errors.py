"""Typed exceptions for everything the esa server (or the connection to it) can report.

Every failure surfaces as an :class:`EsaError` subclass carrying the gRPC status
``code``, the server's ``message`` and, for an error about one item of a batch, the
item's ``index``. Every transport builds them through :func:`error_for`; :func:`esa_error`
maps a ``grpc.RpcError`` or a ``StreamError`` message onto them, reading the failing item
from the error's structured details (never from its message).
"""

from __future__ import annotations

from types import TracebackType
from typing import Protocol, cast

import grpc
from grpc_status import rpc_status

from ._proto.esa.v1 import esa_pb2


class EsaError(Exception):
    """Base class of all esa client errors.

    Attributes:
        code: The gRPC status code the server (or the transport) reported.
        message: The human-readable message, naming what to fix.
        index: The failing item of a batch (its position in the batch), when the error is
            about one item; None otherwise.
    """

    def __init__(
        self,
        message: str,
        code: grpc.StatusCode = grpc.StatusCode.UNKNOWN,
        *,
        index: int | None = None,
    ) -> None:
        """Creates the error from the server's message, status code and failing item."""
        super().__init__(f"{message} [{code.name}]")
        self.code = code
        self.message = message
        self.index = index


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


def error_for(code: grpc.StatusCode | int, message: str, index: int | None = None) -> EsaError:
    """The typed exception for a failure, whichever transport reported it.

    Args:
        code: The gRPC status code, or its number (as ``StreamError.code`` and the
            in-process engine's errors carry it).
        message: What went wrong; empty gives the code's name.
        index: The failing batch item, or None.

    Returns:
        The matching :class:`EsaError` subclass; unknown codes give a plain :class:`EsaError`.
    """
    if not isinstance(code, grpc.StatusCode):
        code = _BY_NUMBER.get(code, grpc.StatusCode.UNKNOWN)
    return _BY_CODE.get(code, EsaError)(message or code.name.lower(), code, index=index)


def esa_error(source: grpc.RpcError | esa_pb2.StreamError) -> EsaError:
    """Maps a failed gRPC call or a ``StreamError`` to the matching :class:`EsaError` subclass.

    Args:
        source: A ``grpc.RpcError`` raised by a call (it also implements ``grpc.Call``),
            or a ``StreamError`` message (gRPC code number, message and failing item).

    Returns:
        The typed exception, ready to raise; unknown codes give a plain :class:`EsaError`.
    """
    if isinstance(source, grpc.RpcError):
        if not (hasattr(source, "code") and hasattr(source, "details")):
            return EsaError(str(source) or "unknown gRPC error")
        # A failed call raises an RpcError that is also its grpc.Call (stubs cannot say both).
        call = cast(grpc.Call, source)
        return error_for(call.code(), call.details() or "", _batch_item(call))
    index = source.item.index if source.HasField("item") else None
    return error_for(source.code, source.message, index)


def _batch_item(call: grpc.Call) -> int | None:
    """The failing item named in a status's details (``esa.v1.BatchItem``), if any."""
    try:
        status = rpc_status.from_call(call)
    except ValueError:  # details that contradict the status: not the server's
        return None
    if status is None:
        return None
    item = esa_pb2.BatchItem()
    for detail in status.details:
        if detail.Unpack(item):
            return item.index
    return None


class StatusLike(Protocol):
    """What ``esa_client._native``'s ``EngineError`` and ``StatusError`` carry."""

    code: int
    message: str
    index: int | None


class TypedErrors:
    """A context that re-raises ``esa_client._native``'s errors as the server's typed ones.

    A class rather than ``contextlib.contextmanager``: it runs on every round trip, and a
    generator-based context costs about as much as the in-process engine's own call.

    Args:
        native: The extension's exception class whose instances to translate (their
            ``code``, ``message`` and ``index`` go to :func:`error_for`).
    """

    def __init__(self, native: type[Exception]) -> None:
        """Translates ``native``'s instances."""
        self._native = native

    def __enter__(self) -> None:
        """Nothing to set up."""
        return None

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        """Raises the typed error of a native one; lets any other pass."""
        if isinstance(error, self._native):
            status = cast(StatusLike, error)
            raise error_for(status.code, status.message, status.index) from None
        # A step out of uint64's range: a ValueError, as protobuf raises it for the wire.
        if isinstance(error, OverflowError):
            raise ValueError(f"step: expected an integer in [0, 2^64), {error}") from None
