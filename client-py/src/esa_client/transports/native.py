"""The transport over gRPC through the Rust client of ``esa_client._native``.

``esa_client._native.GrpcClient`` is esa-proto's tonic client on a private runtime that the
calling thread drives itself, with the GIL released while a call waits: a round trip costs
no thread hand-off and no Python-level message building (numpy arrays go straight into the
request). It speaks the same ``esa.v1`` calls as :class:`~esa_client.transports.grpcio.
GrpcTransport` and raises the same :class:`~esa_client.errors.EsaError` subclasses with the
same failing item. It has no TLS. A batch opened with ``use_stream`` sends its calls as
messages of a ``StepStream`` of its own, and the pipelined pair (a deferred report and the
next probe) as two messages before reading either answer: one round trip, about a third of
the two unary calls' time on a Unix socket (``bench/NOTES.md``). A batch without a stream
makes ``ProbeBatch`` / ``ReportBatch`` calls.
"""

from __future__ import annotations

from collections.abc import Sequence

from .._native import GrpcBatch, GrpcClient, StatusError
from ..errors import TypedErrors
from ..state import F64Array
from .base import BatchProbe, BatchReport, InTurnBatch, LinearCritic, PipelinedBatch
from .native_calls import NativeSessionCalls

_typed_errors = TypedErrors(StatusError)


class NativeGrpcBatch(InTurnBatch):
    """A batch's round trips through the Rust client (unary calls, or its StepStream)."""

    def __init__(self, batch: GrpcBatch) -> None:
        """Sends through ``batch`` (its ids and action dimension fixed)."""
        self._batch = batch

    def probe(self, request: BatchProbe) -> tuple[F64Array, F64Array]:
        """Sends one ProbeBatch."""
        with _typed_errors:
            return self._batch.probe(
                request.steps, request.actions, request.episode_starts, request.action_scales
            )

    def report(self, request: BatchReport) -> F64Array:
        """Sends one ReportBatch."""
        with _typed_errors:
            return self._batch.report(request.steps, request.q_values, request.q_references)

    def close(self) -> None:
        """Ends the batch's StepStream, if it has one; the sessions stay."""
        self._batch.close()


class NativeGrpcStepBatch(NativeGrpcBatch, PipelinedBatch):
    """A :class:`NativeGrpcBatch` on a ``StepStream``, whose pair takes one round trip.

    It also sends a whole step (for a linear critic, or with the critic's values) without
    waiting for its answer (:class:`~esa_client.transports.base.AheadBatch`).
    """

    def _pipelined(self, report: BatchReport, probe: BatchProbe) -> tuple[F64Array, F64Array]:
        with _typed_errors:
            return self._batch.report_then_probe(
                report.steps,
                report.q_values,
                report.q_references,
                probe.steps,
                probe.actions,
                probe.episode_starts,
                probe.action_scales,
            )

    def send_step_linear(self, request: BatchProbe, critic: LinearCritic, paired: bool) -> None:
        """Sends the step's probe, ``critic`` and report as one message; returns at once."""
        with _typed_errors:
            self._batch.send_step_linear(
                request.steps,
                request.actions,
                request.episode_starts,
                request.action_scales,
                critic.gain,
                critic.offset,
                paired,
            )

    def send_step(
        self, request: BatchProbe, q_values: F64Array, q_references: F64Array | None
    ) -> None:
        """Sends the step's probe and the critic's values at it as one message; returns at once."""
        with _typed_errors:
            self._batch.send_step(
                request.steps,
                request.actions,
                request.episode_starts,
                request.action_scales,
                q_values,
                q_references,
            )

    def receive_step(self) -> tuple[F64Array, F64Array, F64Array]:
        """The oldest unanswered step's ``(probes, applied, shifts)``, or its error."""
        with _typed_errors:
            return self._batch.receive_step()


class NativeGrpcTransport(NativeSessionCalls):
    """The :class:`~esa_client.transports.base.Transport` over ``esa_client._native.GrpcClient``.

    Args:
        address: ``host:port`` or ``unix:/path/to/socket`` (checked by the caller).
        timeout: Deadline in seconds of every call.
        token: Sent as ``authorization: Bearer <token>`` with every call; None sends none.

    Attributes:
        client: The Rust client (connecting lazily).
    """

    def __init__(self, address: str, timeout: float, token: str | None = None) -> None:
        """Opens the client (connecting on the first call)."""
        self.client = GrpcClient(address, timeout, token)
        super().__init__(self.client, _typed_errors)

    def open_batch(
        self, ids: Sequence[str], action_dim: int, *, use_stream: bool
    ) -> NativeGrpcBatch:
        """A :class:`NativeGrpcStepBatch` with ``use_stream``, else a :class:`NativeGrpcBatch`."""
        batch = self.client.batch(list(ids), action_dim, use_stream)
        return NativeGrpcStepBatch(batch) if use_stream else NativeGrpcBatch(batch)

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
