"""Typed exceptions for everything the esa server (or the connection to it) can report.

Every transport builds them with :func:`error_for` from the code and failing item as data,
never read from a message.
"""

from __future__ import annotations

import enum
from types import TracebackType
from typing import Any, Protocol, cast

from ._proto.esa.v1 import esa_pb2


class StatusCode(enum.IntEnum):
    """The esa contract's status codes: gRPC's canonical names and numbers, without grpcio."""

    OK = 0
    CANCELLED = 1
    UNKNOWN = 2
    INVALID_ARGUMENT = 3
    DEADLINE_EXCEEDED = 4
    NOT_FOUND = 5
    ALREADY_EXISTS = 6
    PERMISSION_DENIED = 7
    RESOURCE_EXHAUSTED = 8
    FAILED_PRECONDITION = 9
    ABORTED = 10
    OUT_OF_RANGE = 11
    UNIMPLEMENTED = 12
    INTERNAL = 13
    UNAVAILABLE = 14
    DATA_LOSS = 15
    UNAUTHENTICATED = 16

    @classmethod
    def of(cls, number: int) -> StatusCode:
        """The code of ``number``; an unknown number gives ``UNKNOWN``."""
        try:
            return cls(number)
        except ValueError:
            return cls.UNKNOWN


class EsaError(Exception):
    """Base class of all esa client errors, whatever the transport.

    Attributes:
        code: The :class:`StatusCode` the server (or the transport) reported.
        message: The human-readable message, naming what to fix.
        index: The failing item's position in a batch, if the error is about one; else None.
    """

    def __init__(
        self,
        message: str,
        code: StatusCode = StatusCode.UNKNOWN,
        *,
        index: int | None = None,
    ) -> None:
        """Creates the error from the server's message, status code and failing item."""
        super().__init__(f"{message} [{code.name}]")
        self.code = code
        self.message = message
        self.index = index

    def __reduce__(self) -> tuple[Any, ...]:
        """Pickles the message, code and index (Ray and multiprocessing re-raise copies)."""
        return (_rebuild, (type(self), self.message, self.code, self.index))


def _rebuild(cls: type[EsaError], message: str, code: StatusCode, index: int | None) -> EsaError:
    """The error :meth:`EsaError.__reduce__` describes (keyword ``index``)."""
    return cls(message, code, index=index)


class SessionNotFound(EsaError, LookupError):
    """The session id is unknown, closed or expired (``NOT_FOUND``)."""


class InvalidArgument(EsaError, ValueError):
    """The request was malformed: bad config, wrong length, NaN, ... (``INVALID_ARGUMENT``)."""


class StepMismatch(EsaError):
    """The step does not match the session, or a report had no probe (``FAILED_PRECONDITION``)."""


class ResourceExhausted(EsaError):
    """A server limit is reached (``RESOURCE_EXHAUSTED``).

    The message names the limit (``--max-sessions``, ``--max-session-memory``,
    ``--max-message-bytes`` or ``--max-request-memory``).
    """


class Unauthenticated(EsaError, PermissionError):
    """The server wants an auth token and got none or another one (``UNAUTHENTICATED``)."""


class SessionAlreadyExists(EsaError):
    """The session id exists with a different config (``ALREADY_EXISTS``)."""


class ServerUnavailable(EsaError, ConnectionError):
    """The server cannot be reached or the connection was lost (``UNAVAILABLE``)."""


class DeadlineExceeded(EsaError, TimeoutError):
    """The server did not answer within the call's deadline (``DEADLINE_EXCEEDED``)."""


_BY_CODE: dict[StatusCode, type[EsaError]] = {
    StatusCode.NOT_FOUND: SessionNotFound,
    StatusCode.INVALID_ARGUMENT: InvalidArgument,
    StatusCode.FAILED_PRECONDITION: StepMismatch,
    StatusCode.RESOURCE_EXHAUSTED: ResourceExhausted,
    StatusCode.ALREADY_EXISTS: SessionAlreadyExists,
    StatusCode.UNAUTHENTICATED: Unauthenticated,
    StatusCode.UNAVAILABLE: ServerUnavailable,
    StatusCode.DEADLINE_EXCEEDED: DeadlineExceeded,
}


def error_for(code: StatusCode | int, message: str, index: int | None = None) -> EsaError:
    """The typed exception for a failure, whichever transport reported it.

    The :class:`EsaError` subclass of ``code`` (plain ``EsaError`` for an unknown one), with
    ``message`` (empty: the code's name) and the failing batch item ``index``.
    """
    status = code if isinstance(code, StatusCode) else StatusCode.of(code)
    return _BY_CODE.get(status, EsaError)(message or status.name.lower(), status, index=index)


def esa_error(source: esa_pb2.StreamError) -> EsaError:
    """The typed exception of a ``StreamError`` (as a ``StepStream`` or a Zenoh reply carries)."""
    index = source.item.index if source.HasField("item") else None
    return error_for(source.code, source.message, index)


class StatusLike(Protocol):
    """What ``esa_client._native``'s ``EngineError`` and ``StatusError`` carry."""

    code: int
    message: str
    index: int | None


class TypedErrors:
    """A context that re-raises ``esa_client._native``'s errors as the server's typed ones.

    A class, not ``contextlib.contextmanager``: it runs on every round trip, and a generator
    context costs about as much as the in-process engine's own call.
    """

    def __init__(self, native: type[Exception]) -> None:
        """Translates ``native``'s instances."""
        self._native = native

    def __enter__(self) -> None:
        """Nothing to set up."""

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
