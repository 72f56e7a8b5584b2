"""How requests reach the server: unary calls with deadlines, and a persistent StepStream.

Both transports expose ``probe_batch`` / ``report_batch`` / ``report_then_probe`` so
:class:`esa_client.SessionBatch` does not care which one carries its round trips. Every
wait is bounded by the client's timeout and every failure becomes an
:class:`esa_client.errors.EsaError`. ``report_then_probe`` is the pipelined step of
CONTRACT.md section 1b: on the StepStream both messages go out before either answer is
read, so a step costs one round trip.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable
from typing import Any, TypeVar

import grpc

from ._proto.esa.v1 import esa_pb2, esa_pb2_grpc
from .errors import DeadlineExceeded, EsaError, ServerUnavailable, esa_error

Response = TypeVar("Response")


def call(rpc: Callable[..., Response], request: Any, timeout: float) -> Response:
    """Performs one unary call with a deadline, raising typed errors.

    Args:
        rpc: A unary-unary method of a generated stub.
        request: The request message.
        timeout: Deadline in seconds.

    Returns:
        The response message.

    Raises:
        EsaError: The matching subclass for any failure (see :func:`esa_error`).
    """
    try:
        return rpc(request, timeout=timeout)
    except grpc.RpcError as err:
        raise esa_error(err) from None


class UnaryTransport:
    """Batch round trips over the ``ProbeBatch`` / ``ReportBatch`` unary RPCs."""

    def __init__(self, stub: esa_pb2_grpc.EsaServiceStub, timeout: float) -> None:
        """Wraps ``stub``; every call gets ``timeout`` seconds."""
        self._stub = stub
        self._timeout = timeout

    def probe_batch(self, request: esa_pb2.ProbeBatchRequest) -> esa_pb2.ProbeBatchResponse:
        """Sends one ProbeBatch."""
        return call(self._stub.ProbeBatch, request, self._timeout)

    def report_batch(self, request: esa_pb2.ReportBatchRequest) -> esa_pb2.ReportBatchResponse:
        """Sends one ReportBatch."""
        return call(self._stub.ReportBatch, request, self._timeout)

    def report_then_probe(
        self, report: esa_pb2.ReportBatchRequest, probe: esa_pb2.ProbeBatchRequest
    ) -> tuple[esa_pb2.ReportBatchResponse, esa_pb2.ProbeBatchResponse]:
        """Sends the ReportBatch, then the ProbeBatch (two unary round trips)."""
        return self.report_batch(report), self.probe_batch(probe)

    def close(self) -> None:
        """Nothing to release."""


class StepMessages:
    """Batch round trips as ``StepStream`` messages; subclasses carry one message each way.

    A ``StepStreamResponse`` may carry an in-band ``error``, raised here as its typed
    exception.
    """

    def _exchange(self, request: esa_pb2.StepStreamRequest) -> esa_pb2.StepStreamResponse:
        raise NotImplementedError

    def _exchange_pair(
        self, first: esa_pb2.StepStreamRequest, second: esa_pb2.StepStreamRequest
    ) -> tuple[esa_pb2.StepStreamResponse, esa_pb2.StepStreamResponse]:
        """Both answers, in order; one after the other unless a subclass pipelines them."""
        return self._exchange(first), self._exchange(second)

    def _round_trip(self, request: esa_pb2.StepStreamRequest) -> esa_pb2.StepStreamResponse:
        return _checked(self._exchange(request))

    def report_then_probe(
        self, report: esa_pb2.ReportBatchRequest, probe: esa_pb2.ProbeBatchRequest
    ) -> tuple[esa_pb2.ReportBatchResponse, esa_pb2.ProbeBatchResponse]:
        """Sends the ReportBatch and the ProbeBatch as two messages; raises the first error.

        A probe that starts a new episode for every session would succeed even after its
        report failed, leaving the report unrecoverable: that pair goes one message at a
        time, so a failed report stops the probe (once per episode end, not per step).
        """
        if probe.episode_starts and all(probe.episode_starts):
            return self.report_batch(report), self.probe_batch(probe)
        first, second = self._exchange_pair(
            esa_pb2.StepStreamRequest(report_batch=report),
            esa_pb2.StepStreamRequest(probe_batch=probe),
        )
        return _checked(first).report_batch, _checked(second).probe_batch

    def probe_batch(self, request: esa_pb2.ProbeBatchRequest) -> esa_pb2.ProbeBatchResponse:
        """Sends one ProbeBatch as a StepStream message."""
        return self._round_trip(esa_pb2.StepStreamRequest(probe_batch=request)).probe_batch

    def report_batch(self, request: esa_pb2.ReportBatchRequest) -> esa_pb2.ReportBatchResponse:
        """Sends one ReportBatch as a StepStream message."""
        return self._round_trip(esa_pb2.StepStreamRequest(report_batch=request)).report_batch


def _checked(response: esa_pb2.StepStreamResponse) -> esa_pb2.StepStreamResponse:
    """The response, or its in-band ``error`` raised as the typed exception."""
    if response.HasField("error"):
        raise esa_error(response.error)
    return response


_END = object()


class StreamTransport(StepMessages):
    """Batch round trips over one long-lived ``StepStream``.

    gRPC's blocking stream iterator has no per-message deadline, so a reader thread
    moves responses into a queue that the caller waits on with the timeout. After a
    timeout or a transport failure the stream is out of step with its requests, so
    it is dropped and the next call opens a new one; that is safe because the
    server accepts a repeated probe or report for the same step (CONTRACT.md).
    """

    def __init__(self, stub: esa_pb2_grpc.EsaServiceStub, timeout: float) -> None:
        """Prepares the transport; the stream opens on first use."""
        self._stub = stub
        self._timeout = timeout
        self._requests: queue.SimpleQueue[object] | None = None
        self._responses: queue.SimpleQueue[object] = queue.SimpleQueue()
        self._call: Any = None

    def _open(self) -> None:
        requests: queue.SimpleQueue[object] = queue.SimpleQueue()
        responses: queue.SimpleQueue[object] = queue.SimpleQueue()
        stream = self._stub.StepStream(iter(requests.get, _END))

        def read() -> None:
            try:
                for response in stream:
                    responses.put(response)
                responses.put(ServerUnavailable("the server closed the StepStream"))
            except grpc.RpcError as err:
                responses.put(esa_error(err))

        threading.Thread(target=read, name="esa-step-stream", daemon=True).start()
        self._requests, self._responses, self._call = requests, responses, stream

    def _drop(self) -> None:
        if self._call is not None:
            self._call.cancel()
            # Unblocks gRPC's request-consuming thread, which waits on this queue.
            self._requests.put(_END)  # type: ignore[union-attr]
        self._requests, self._call = None, None

    def _exchange(self, request: esa_pb2.StepStreamRequest) -> esa_pb2.StepStreamResponse:
        return self._exchange_all([request])[0]

    def _exchange_pair(
        self, first: esa_pb2.StepStreamRequest, second: esa_pb2.StepStreamRequest
    ) -> tuple[esa_pb2.StepStreamResponse, esa_pb2.StepStreamResponse]:
        """Writes both messages before reading: one round trip for the pair."""
        a, b = self._exchange_all([first, second])
        return a, b

    def _exchange_all(
        self, requests: list[esa_pb2.StepStreamRequest]
    ) -> list[esa_pb2.StepStreamResponse]:
        if self._call is None:
            self._open()
        for request in requests:
            self._requests.put(request)  # type: ignore[union-attr]
        answers = []
        for _ in requests:
            try:
                item = self._responses.get(timeout=self._timeout)
            except queue.Empty:
                self._drop()
                raise DeadlineExceeded(
                    f"no StepStream response within {self._timeout} s",
                    grpc.StatusCode.DEADLINE_EXCEEDED,
                ) from None
            if isinstance(item, EsaError):
                self._drop()
                raise item
            answers.append(item)
        return answers  # type: ignore[return-value]

    def close(self) -> None:
        """Ends the stream."""
        self._drop()
