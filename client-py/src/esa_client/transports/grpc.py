"""The transport over gRPC, through the Rust client of ``esa_client._native``.

``esa_client._native.GrpcClient`` is esa-client's tonic client on a private runtime that the
calling thread drives itself, with the GIL released while a call waits: a round trip costs
no thread hand-off and no Python-level message building (numpy arrays go straight into the
request). It raises the :class:`~esa_client.errors.EsaError` subclass of the server's status
code, with the failing item; it speaks TLS and mutual TLS (rustls, :class:`TlsConfig`), sends
the auth token with every call and asks the server's health service whether it serves. A
batch opened with ``use_stream`` sends its calls as messages of a ``StepStream`` of its own,
and the pipelined pair (a deferred report and the next probe) as two messages before reading
either answer: one round trip, about a third of the two unary calls' time on a Unix socket
(BENCHMARKS.md's section 1b rows). A batch without a stream makes ``ProbeBatch`` /
``ReportBatch`` calls.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from .._native import GrpcBatch as NativeBatch
from .._native import GrpcClient, StatusError
from ..errors import TypedErrors
from ..state import F64Array, SessionProgress
from .base import BatchProbe, BatchReport, BatchTransport, LinearCritic, PipelinedBatch
from .native_calls import NativeSessionCalls
from .stepping import AheadStepper

_typed_errors = TypedErrors(StatusError)


@dataclass(frozen=True)
class TlsConfig:
    """TLS for the connection to a server started with ``--tls-cert`` and ``--tls-key``.

    Connect to a host name (or IP address) that the server's certificate names; a failed
    handshake (untrusted server, refused client certificate) raises ``ServerUnavailable``.

    Args:
        ca: PEM file of the CA(s) that issued the server's certificate; None trusts the
            Mozilla roots (webpki-roots).
        cert: PEM file of this client's certificate, for a server started with
            ``--tls-client-ca`` (mutual TLS); needs ``key``.
        key: PEM file of the certificate's private key.
        server_name: The name to check the server's certificate against instead of the
            address's host (e.g. when connecting through a tunnel).
    """

    ca: str | os.PathLike[str] | None = None
    cert: str | os.PathLike[str] | None = None
    key: str | os.PathLike[str] | None = None
    server_name: str | None = None

    def __post_init__(self) -> None:
        """Checks that ``cert`` and ``key`` come together."""
        if (self.cert is None) != (self.key is None):
            raise ValueError(
                f"expected both cert and key (mutual TLS) or neither, "
                f"got cert={self.cert!r}, key={self.key!r}"
            )

    def pems(self) -> tuple[bytes | None, bytes | None, bytes | None]:
        """The contents of ``ca``, ``cert`` and ``key`` (None for those not given), read now.

        Raises:
            OSError: If a file cannot be read.
        """

        def read(path: str | os.PathLike[str] | None) -> bytes | None:
            return None if path is None else Path(path).read_bytes()

        return read(self.ca), read(self.cert), read(self.key)


class GrpcBatch(BatchTransport):
    """A batch's round trips through the Rust client (unary calls, or its StepStream)."""

    def __init__(self, batch: NativeBatch) -> None:
        """Sends through ``batch`` (its ids and action dimension fixed)."""
        self._batch = batch

    def probe(self, request: BatchProbe) -> tuple[F64Array, F64Array]:
        """Sends one ProbeBatch."""
        with _typed_errors:
            return self._batch.probe(*request)

    def report(self, request: BatchReport) -> F64Array:
        """Sends one ReportBatch."""
        with _typed_errors:
            return self._batch.report(*request)

    def close(self) -> None:
        """Ends the batch's StepStream, if it has one; the sessions stay."""
        self._batch.close()

    def progress(self) -> list[SessionProgress] | None:
        """Each session's progress in the last answer that carried it; None before one."""
        seen = self._batch.progress()
        return None if seen is None else SessionProgress.from_batch_answer(*seen)


class GrpcStepBatch(GrpcBatch, PipelinedBatch):
    """A :class:`GrpcBatch` on a ``StepStream``, whose pair takes one round trip.

    It also sends a whole step (for a linear critic, or with the critic's values) without
    waiting for its answer (:class:`~esa_client.transports.stepping.AheadBatch`).
    """

    def _pipelined(self, report: BatchReport, probe: BatchProbe) -> tuple[F64Array, F64Array]:
        with _typed_errors:
            return self._batch.report_then_probe(*(report + probe))

    def stepper(self) -> AheadStepper:
        """Its stream thread sends steps ahead of their answers."""
        return AheadStepper(self)

    def send_step_linear(self, request: BatchProbe, critic: LinearCritic, paired: bool) -> None:
        """Sends the step's probe, ``critic`` and report as one message; returns at once."""
        with _typed_errors:
            self._batch.send_step_linear(*request, critic.gain, critic.offset, paired)

    def send_step(
        self, request: BatchProbe, q_values: F64Array, q_references: F64Array | None
    ) -> None:
        """Sends the step's probe and the critic's values at it as one message; returns at once."""
        with _typed_errors:
            self._batch.send_step(*request, q_values, q_references)

    def receive_step(self) -> tuple[F64Array, F64Array, F64Array]:
        """The oldest unanswered step's ``(probes, applied, shifts)``, or its error."""
        with _typed_errors:
            return self._batch.receive_step()

    def resend_step(self) -> None:
        """Sends the step whose answer the wire lost again, on a new stream; returns at once.

        For a step the server did not apply (its sessions are still where they were before
        it): its answer is then read with :meth:`receive_step`.
        """
        with _typed_errors:
            self._batch.resend_step()


class GrpcTransport(NativeSessionCalls):
    """The :class:`~esa_client.transports.base.Transport` over ``esa_client._native.GrpcClient``.

    Args:
        address: ``host:port`` or ``unix:/path/to/socket`` (checked by the caller).
        timeout: Deadline in seconds of every call.
        token: Sent as ``authorization: Bearer <token>`` with every call; None sends none.
        tls: Connect over TLS; None connects in plaintext.

    Attributes:
        client: The Rust client (connecting lazily).
        tls: The TLS settings, or None.

    Raises:
        ValueError: A malformed timeout, token or TLS setting.
        OSError: If a TLS file cannot be read.
    """

    def __init__(
        self, address: str, timeout: float, token: str | None = None, tls: TlsConfig | None = None
    ) -> None:
        """Opens the client (connecting on the first call)."""
        self.tls = tls
        if tls is None:
            self.client = GrpcClient(address, timeout, token)
        else:
            ca, cert, key = tls.pems()
            self.client = GrpcClient(
                address, timeout, token, tls=True, ca=ca, cert=cert, key=key, domain=tls.server_name
            )
        super().__init__(self.client, _typed_errors)

    def open_batch(self, ids: Sequence[str], action_dim: int, *, use_stream: bool) -> GrpcBatch:
        """A :class:`GrpcStepBatch` with ``use_stream``, else a :class:`GrpcBatch`."""
        batch = self.client.batch(list(ids), action_dim, use_stream)
        return GrpcStepBatch(batch) if use_stream else GrpcBatch(batch)

    def healthy(self, timeout: float, *, wait_for_ready: bool = False) -> bool:
        """Asks the server's ``grpc.health.v1.Health`` service whether it is serving.

        Args:
            timeout: Deadline in seconds.
            wait_for_ready: Retry (up to the deadline) while the server is not reachable yet.
        """
        return self.client.healthy(timeout, wait_for_ready)

    def close(self) -> None:
        """Drops the connection. Idempotent."""
        self.client.close()

    def __repr__(self) -> str:
        """Names the transport (the client shows the address)."""
        return "GrpcTransport()" if self.tls is None else "GrpcTransport(tls)"
