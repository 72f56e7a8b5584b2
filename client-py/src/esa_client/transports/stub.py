"""The :class:`~esa_client.transports.base.Transport` over protobuf messages, for any wire.

:class:`StubTransport` turns the protocol's calls and arrays into ``esa.v1`` request
messages and sends them through a *stub*: any object with one callable per RPC in the
calling convention of the generated ``EsaServiceStub`` (``stub.Probe(request,
timeout=...)``). gRPC's generated stub is one (:mod:`esa_client.transports.grpcio`), the
Zenoh stub another (:mod:`esa_client.transports.zenoh_query`). Batches go as ``ProbeBatch`` /
``ReportBatch`` calls, or as ``StepStream`` messages over a :class:`StepExchange`, which
the wire provides (one bidirectional gRPC stream, or one Zenoh query per message).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Protocol, TypeVar, cast

import grpc
import numpy as np
from grpc_status import rpc_status

from .._proto.esa.v1 import esa_pb2
from ..errors import EsaError, error_for, esa_error
from ..state import F64Array, SessionState
from .base import BatchProbe, BatchReport, BatchTransport, InTurnBatch, PipelinedBatch

Request = TypeVar("Request", contravariant=True)
Response = TypeVar("Response", covariant=True)
Answer = TypeVar("Answer")


class UnaryRpc(Protocol[Request, Response]):
    """One unary RPC of a stub: ``rpc(request, timeout=...) -> response``."""

    def __call__(self, request: Request, timeout: float | None = None) -> Response:
        """Sends ``request``; returns the response or raises (``grpc.RpcError`` or EsaError)."""
        ...


class ServiceStub(Protocol):
    """The unary RPCs of ``esa.v1.EsaService`` in the generated stub's calling convention."""

    @property
    def CreateSession(  # noqa: N802 (the RPC's name)
        self,
    ) -> UnaryRpc[esa_pb2.CreateSessionRequest, esa_pb2.CreateSessionResponse]:
        """The ``CreateSession`` RPC."""
        ...

    @property
    def Probe(self) -> UnaryRpc[esa_pb2.ProbeRequest, esa_pb2.ProbeResponse]:  # noqa: N802
        """The ``Probe`` RPC."""
        ...

    @property
    def Report(self) -> UnaryRpc[esa_pb2.ReportRequest, esa_pb2.ReportResponse]:  # noqa: N802
        """The ``Report`` RPC."""
        ...

    @property
    def EndEpisode(  # noqa: N802
        self,
    ) -> UnaryRpc[esa_pb2.EndEpisodeRequest, esa_pb2.EndEpisodeResponse]:
        """The ``EndEpisode`` RPC."""
        ...

    @property
    def CloseSession(  # noqa: N802
        self,
    ) -> UnaryRpc[esa_pb2.CloseSessionRequest, esa_pb2.CloseSessionResponse]:
        """The ``CloseSession`` RPC."""
        ...

    @property
    def GetSession(  # noqa: N802
        self,
    ) -> UnaryRpc[esa_pb2.GetSessionRequest, esa_pb2.GetSessionResponse]:
        """The ``GetSession`` RPC."""
        ...

    @property
    def ProbeBatch(  # noqa: N802
        self,
    ) -> UnaryRpc[esa_pb2.ProbeBatchRequest, esa_pb2.ProbeBatchResponse]:
        """The ``ProbeBatch`` RPC."""
        ...

    @property
    def ReportBatch(  # noqa: N802
        self,
    ) -> UnaryRpc[esa_pb2.ReportBatchRequest, esa_pb2.ReportBatchResponse]:
        """The ``ReportBatch`` RPC."""
        ...


def call(rpc: UnaryRpc[Request, Answer], request: Request, timeout: float) -> Answer:
    """Performs one unary call with a deadline, raising typed errors.

    Args:
        rpc: A unary method of a stub.
        request: The request message.
        timeout: Deadline in seconds.

    Returns:
        The response message.

    Raises:
        EsaError: The matching subclass for any failure (see :func:`rpc_error`).
    """
    try:
        return rpc(request, timeout=timeout)
    except grpc.RpcError as err:
        raise rpc_error(err) from None


def rpc_error(error: grpc.RpcError) -> EsaError:
    """The typed exception of a failed grpcio call, with the failing item of its details.

    Args:
        error: A ``grpc.RpcError`` raised by a call (it also implements ``grpc.Call``).

    Returns:
        The matching :class:`~esa_client.errors.EsaError` subclass, ready to raise.
    """
    if not (hasattr(error, "code") and hasattr(error, "details")):
        return EsaError(str(error) or "unknown gRPC error")
    # A failed call raises an RpcError that is also its grpc.Call (stubs cannot say both).
    failed = cast(grpc.Call, error)
    return error_for(failed.code().value[0], failed.details() or "", _batch_item(failed))


def _batch_item(failed: grpc.Call) -> int | None:
    """The failing item named in a status's details (``esa.v1.BatchItem``), if any."""
    try:
        status = rpc_status.from_call(failed)
    except ValueError:  # details that contradict the status: not the server's
        return None
    if status is None:
        return None
    item = esa_pb2.BatchItem()
    for detail in status.details:
        if detail.Unpack(item):
            return item.index
    return None


class StepExchange(Protocol):
    """Carries ``StepStream`` messages: one response per request, in order."""

    def exchange(
        self, requests: Sequence[esa_pb2.StepStreamRequest]
    ) -> list[esa_pb2.StepStreamResponse]:
        """Sends the requests (all before reading, where the wire allows) and returns the answers.

        In-band ``error`` answers are returned, not raised; a failure of the wire itself
        raises its :class:`~esa_client.errors.EsaError`.
        """
        ...

    def close(self) -> None:
        """Releases the stream, if any."""
        ...


def probe_batch_request(ids: Sequence[str], probe: BatchProbe) -> esa_pb2.ProbeBatchRequest:
    """The ``ProbeBatchRequest`` of ``probe`` for the sessions ``ids``."""
    return esa_pb2.ProbeBatchRequest(
        session_ids=ids,
        steps=probe.steps.tolist(),
        actions=probe.actions.ravel().tolist(),
        episode_starts=probe.episode_starts.tolist(),
        action_scales=[] if probe.action_scales is None else probe.action_scales.ravel().tolist(),
    )


def report_batch_request(ids: Sequence[str], report: BatchReport) -> esa_pb2.ReportBatchRequest:
    """The ``ReportBatchRequest`` of ``report`` for the sessions ``ids``."""
    return esa_pb2.ReportBatchRequest(
        session_ids=ids,
        steps=report.steps.tolist(),
        q_values=report.q_values.tolist(),
        q_references=[] if report.q_references is None else report.q_references.tolist(),
    )


def _values(values: Sequence[float], shape: tuple[int, int]) -> F64Array:
    return np.array(values, dtype=np.float64).reshape(shape)


class _Batch:
    """What both batch kinds share: the ids and the ``(N, D)`` shape of the answers."""

    def __init__(self, ids: Sequence[str], action_dim: int) -> None:
        self._ids = tuple(ids)
        self._shape = (len(self._ids), action_dim)

    def _probe_answer(self, response: esa_pb2.ProbeBatchResponse) -> tuple[F64Array, F64Array]:
        return _values(response.probes, self._shape), _values(response.actions, self._shape)

    def _report_answer(self, response: esa_pb2.ReportBatchResponse) -> F64Array:
        return _values(response.actions, self._shape)


class UnaryBatch(_Batch, InTurnBatch):
    """A batch's round trips as ``ProbeBatch`` / ``ReportBatch`` calls (two for the pair)."""

    def __init__(
        self, stub: ServiceStub, ids: Sequence[str], action_dim: int, timeout: float
    ) -> None:
        """Sends through ``stub``; every call gets ``timeout`` seconds."""
        super().__init__(ids, action_dim)
        self._stub = stub
        self._timeout = timeout

    def probe(self, request: BatchProbe) -> tuple[F64Array, F64Array]:
        """Sends one ProbeBatch."""
        message = probe_batch_request(self._ids, request)
        return self._probe_answer(call(self._stub.ProbeBatch, message, self._timeout))

    def report(self, request: BatchReport) -> F64Array:
        """Sends one ReportBatch."""
        message = report_batch_request(self._ids, request)
        return self._report_answer(call(self._stub.ReportBatch, message, self._timeout))


def _checked(response: esa_pb2.StepStreamResponse) -> esa_pb2.StepStreamResponse:
    """The response, or its in-band ``error`` raised as the typed exception."""
    if response.HasField("error"):
        raise esa_error(response.error)
    return response


class StepBatch(_Batch, PipelinedBatch):
    """A batch's round trips as ``StepStream`` messages; the pair takes one round trip."""

    def __init__(self, exchange: StepExchange, ids: Sequence[str], action_dim: int) -> None:
        """Sends through ``exchange``, which this batch owns."""
        super().__init__(ids, action_dim)
        self._exchange = exchange

    def _round_trip(self, request: esa_pb2.StepStreamRequest) -> esa_pb2.StepStreamResponse:
        return _checked(self._exchange.exchange([request])[0])

    def probe(self, request: BatchProbe) -> tuple[F64Array, F64Array]:
        """Sends one ProbeBatch as a StepStream message."""
        message = esa_pb2.StepStreamRequest(probe_batch=probe_batch_request(self._ids, request))
        return self._probe_answer(self._round_trip(message).probe_batch)

    def report(self, request: BatchReport) -> F64Array:
        """Sends one ReportBatch as a StepStream message."""
        message = esa_pb2.StepStreamRequest(report_batch=report_batch_request(self._ids, request))
        return self._report_answer(self._round_trip(message).report_batch)

    def _pipelined(self, report: BatchReport, probe: BatchProbe) -> tuple[F64Array, F64Array]:
        """Sends the ReportBatch and the ProbeBatch as two messages; raises the first error."""
        first, second = self._exchange.exchange(
            [
                esa_pb2.StepStreamRequest(report_batch=report_batch_request(self._ids, report)),
                esa_pb2.StepStreamRequest(probe_batch=probe_batch_request(self._ids, probe)),
            ]
        )
        _checked(first)
        return self._probe_answer(_checked(second).probe_batch)

    def close(self) -> None:
        """Ends the stream."""
        self._exchange.close()


class StubTransport:
    """The :class:`~esa_client.transports.base.Transport` over a :class:`ServiceStub`.

    Args:
        stub: Sends the unary calls.
        timeout: Deadline in seconds of every call.
        step_exchange: Opens the :class:`StepExchange` of one batch (``use_stream=True``).
    """

    def __init__(
        self,
        stub: ServiceStub,
        timeout: float,
        step_exchange: Callable[[], StepExchange],
    ) -> None:
        """Sends through ``stub``; streamed batches through ``step_exchange()``."""
        self.stub = stub
        self.timeout = timeout
        self._step_exchange = step_exchange

    def create_session(self, session_id: str, config: esa_pb2.SessionConfig) -> str:
        """``CreateSession``; returns the id (the server's UUID for an empty one)."""
        request = esa_pb2.CreateSessionRequest(session_id=session_id, config=config)
        return call(self.stub.CreateSession, request, self.timeout).session_id

    def get_session(self, session_id: str) -> SessionState:
        """``GetSession``."""
        request = esa_pb2.GetSessionRequest(session_id=session_id)
        return SessionState.from_proto(call(self.stub.GetSession, request, self.timeout))

    def close_session(self, session_id: str) -> None:
        """``CloseSession``."""
        request = esa_pb2.CloseSessionRequest(session_id=session_id)
        call(self.stub.CloseSession, request, self.timeout)

    def end_episode(self, session_id: str) -> int:
        """``EndEpisode``; returns the completed-episode count."""
        request = esa_pb2.EndEpisodeRequest(session_id=session_id)
        return call(self.stub.EndEpisode, request, self.timeout).episodes_completed

    def probe(
        self,
        session_id: str,
        step: int,
        action: F64Array,
        episode_start: bool,
        action_scale: F64Array | None,
    ) -> tuple[F64Array, F64Array]:
        """``Probe``; returns the probe and the applied action."""
        request = esa_pb2.ProbeRequest(
            session_id=session_id,
            step=step,
            action=action.tolist(),
            episode_start=episode_start,
            action_scale=[] if action_scale is None else action_scale.tolist(),
        )
        response = call(self.stub.Probe, request, self.timeout)
        return (
            np.array(response.probe, dtype=np.float64),
            np.array(response.action, dtype=np.float64),
        )

    def report(
        self, session_id: str, step: int, q_value: float, q_reference: float | None
    ) -> F64Array:
        """``Report``; returns the improved action."""
        request = esa_pb2.ReportRequest(session_id=session_id, step=step, q_value=q_value)
        if q_reference is not None:
            request.q_reference = q_reference
        response = call(self.stub.Report, request, self.timeout)
        return np.array(response.action, dtype=np.float64)

    def open_batch(
        self, ids: Sequence[str], action_dim: int, *, use_stream: bool
    ) -> BatchTransport:
        """A :class:`StepBatch` over a new exchange, or a :class:`UnaryBatch`."""
        if use_stream:
            return StepBatch(self._step_exchange(), ids, action_dim)
        return UnaryBatch(self.stub, ids, action_dim, self.timeout)
