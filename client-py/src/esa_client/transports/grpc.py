"""The transport over gRPC, through the Rust (tonic) client of ``esa_client._native``.

The calling thread drives the client's runtime, GIL released while a call waits: a round
trip costs no thread hand-off and builds no Python messages.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .._native import EngineError, GrpcClient, StatusError, StepAhead
from .._native import GrpcBatch as NativeBatch
from ..errors import TypedErrors
from ..state import BoolArray, F64Array, I64Array, SessionProgress, check_array
from .base import BatchProbe, BatchReport, BatchTransport, LinearCritic, PipelinedBatch
from .messages import QuadraticCritic
from .native_calls import NativeSessionCalls
from .stepping import Critic, StepCall, Stepper, check_critic

if TYPE_CHECKING:
    from ..session import SessionBatch

_typed_errors = TypedErrors(StatusError)
_engine_errors = TypedErrors(EngineError)


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
        paths = (self.ca, self.cert, self.key)
        ca, cert, key = (None if path is None else Path(path).read_bytes() for path in paths)
        return ca, cert, key


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
    """A :class:`GrpcBatch` on a ``StepStream``: the pair in one round trip, steps sent ahead."""

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
        """The oldest unanswered step's ``(probes, applied, shifts)``; raises its error."""
        with _typed_errors:
            return self._batch.receive_step()

    def resend_step(self) -> None:
        """Sends a step the server did not apply again, on a new stream; returns at once."""
        with _typed_errors:
            self._batch.resend_step()


class AheadStepper(Stepper):
    """A step sent ahead of its answer, which the next call reads.

    esa-core computes the applied actions (and probes) here from the last answer's shifts
    ``v(t)``, so the env's and learner's work overlaps the round trip.
    """

    def __init__(self, ahead: GrpcStepBatch) -> None:
        """Sends steps through ``ahead``."""
        self._ahead = ahead
        # The step sent ahead: the steps and starts it replaced (restored if it fails), and it.
        self._in_flight: tuple[I64Array, BoolArray, BatchProbe] | None = None
        self._shifts: F64Array | None = None  # v(t) of the next step, from the last answer
        self._engine: StepAhead | None = None

    def step(self, batch: SessionBatch, call: StepCall) -> tuple[F64Array | None, F64Array]:
        """The step sent ahead (see :meth:`~esa_client.SessionBatch.step`)."""
        critic, paired = call.critic, call.paired
        if not isinstance(critic, QuadraticCritic):  # esa-core checks it (see _send)
            check_critic(critic, batch.n, batch.action_dim)
        batch.flush()
        ledger = batch.ledger
        request = ledger.probe_request(call.actions, call.episode_starts, None, call.action_scales)
        steps_before, starts_before = ledger.steps, ledger.starts_due.copy()
        request, (probes, applied) = batch.recovery.send_ahead(
            request, lambda sent: self._send(batch, sent, critic, paired)
        )
        self._in_flight = (steps_before, starts_before, request)
        ledger.stepped(request)
        return probes, applied

    def flush(self, batch: SessionBatch) -> None:
        """Reads the shifts ``v(t + 1)`` of the step in flight, if any; a refused step is undone."""
        if self._in_flight is None:
            return
        (steps_before, starts_before, sent), self._in_flight = self._in_flight, None
        ledger = batch.ledger

        def undo() -> None:
            ledger.steps, ledger.starts_due = steps_before, starts_before

        def resend() -> F64Array:
            self._ahead.resend_step()
            return self._ahead.receive_step()[2]

        self._shifts = batch.recovery.receive_ahead(
            lambda: self._ahead.receive_step()[2],
            lambda: batch.recovery.resume_ahead(sent, steps_before, self._ahead.progress(), resend),
            undo,
        )

    def reset(self) -> None:
        """Forgets the step in flight (its answer would be read as the next step's)."""
        if self._in_flight is not None:
            self._in_flight = None
            self._ahead.close()
        self._shifts = None

    def _send(
        self, batch: SessionBatch, request: BatchProbe, critic: Critic, paired: bool
    ) -> tuple[F64Array | None, F64Array]:
        """Sends ``request``'s step, all checked first; returns the probes and the applied."""
        if self._engine is None:
            self._engine = StepAhead([c.to_proto().SerializeToString() for c in batch.configs])
        shifts = np.zeros((batch.n, batch.action_dim)) if self._shifts is None else self._shifts
        if request.episode_starts.any():
            shifts = np.where(request.episode_starts[:, None], 0.0, shifts)
        ahead = (shifts, request.steps, request.actions, request.action_scales)
        if isinstance(critic, QuadraticCritic):  # checked and evaluated as in-process
            try:
                with _engine_errors:
                    probes, applied, q, refs = self._engine.probes_quadratic(*ahead, critic, paired)
            except ValueError:
                check_critic(critic, batch.n, batch.action_dim)  # in every transport's words
                raise
            self._ahead.send_step(request, q, refs)
            return probes, applied
        with _engine_errors:
            probes, applied = self._engine.probes(*ahead)
        if isinstance(critic, LinearCritic):  # the server evaluates it
            self._ahead.send_step_linear(request, critic, paired)
            return None, applied
        points = np.concatenate([probes, applied]) if paired else probes
        q = check_array(critic(points), (len(points),), "critic values", finite=True)
        self._ahead.send_step(request, q[: batch.n], q[batch.n :] if paired else None)
        return probes, applied


class GrpcTransport(NativeSessionCalls):
    """The :class:`~esa_client.transports.base.Transport` over ``esa_client._native.GrpcClient``.

    ``timeout`` is every call's deadline in seconds; ``token`` goes as a Bearer token.

    Raises:
        ValueError: A malformed timeout, token or TLS setting.
        OSError: If a TLS file cannot be read.
    """

    def __init__(
        self, address: str, timeout: float, token: str | None = None, tls: TlsConfig | None = None
    ) -> None:
        """Opens the client (connecting on the first call)."""
        self.tls = tls
        ca, cert, key = (None, None, None) if tls is None else tls.pems()
        domain = None if tls is None else tls.server_name
        self.client = GrpcClient(
            address, timeout, token, tls=tls is not None, ca=ca, cert=cert, key=key, domain=domain
        )
        super().__init__(self.client, _typed_errors)

    def open_batch(self, ids: Sequence[str], action_dim: int, *, use_stream: bool) -> GrpcBatch:
        """A :class:`GrpcStepBatch` with ``use_stream``, else a :class:`GrpcBatch`."""
        batch = self.client.batch(list(ids), action_dim, use_stream)
        return GrpcStepBatch(batch) if use_stream else GrpcBatch(batch)

    def healthy(self, timeout: float, *, wait_for_ready: bool = False) -> bool:
        """Asks the server's ``grpc.health.v1.Health`` service whether it is serving."""
        return self.client.healthy(timeout, wait_for_ready)

    def close(self) -> None:
        """Drops the connection. Idempotent."""
        self.client.close()

    def __repr__(self) -> str:
        """Names the transport (the client shows the address)."""
        return "GrpcTransport()" if self.tls is None else "GrpcTransport(tls)"
