"""Spreading sessions over N ``esa-server`` processes (``--shard i/N``): the transport.

A session lives on exactly one shard (:func:`esa_client.sharding.shard_of`, the routing
rule every client shares), so single-session calls are forwarded as
they are. :class:`ShardedTransport` is the :class:`~esa_client.transports.base.Transport`
over one transport per shard: a batch is split into one sub-batch per shard, the
sub-batches are sent concurrently and the answers merged back into request order.
Each sub-batch is all-or-nothing on its shard; if one shard fails, the others may
have applied their part, and repeating the whole call is safe because a server
treats a repeated probe or report of the same step as a retry (CONTRACT.md). A
shard's error names the failing item by its index in the whole batch.
"""

from __future__ import annotations

import uuid
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Generic, Protocol, TypeVar

import numpy as np

from .._proto.esa.v1 import esa_pb2
from ..errors import EsaError, InvalidArgument, StatusCode
from ..sharding import shard_of
from ..state import F64Array, I64Array, SessionState
from .base import BatchProbe, BatchReport, BatchTransport, Transport
from .stub import ServiceStub, UnaryRpc

Answer = TypeVar("Answer")
Response = TypeVar("Response")


class QueryStub(ServiceStub, Protocol):
    """A stub whose ``StepStream`` is unary (one message in, one out), as over Zenoh."""

    @property
    def StepStream(  # noqa: N802 (the RPC's name)
        self,
    ) -> UnaryRpc[esa_pb2.StepStreamRequest, esa_pb2.StepStreamResponse]:
        """The ``StepStream`` RPC, one message per call."""
        ...


class _ForSession(Protocol):
    """A request naming one session."""

    @property
    def session_id(self) -> str:
        """The session's id."""
        ...


SessionRequest = TypeVar("SessionRequest", bound=_ForSession)
BatchRequest = TypeVar("BatchRequest")


class _ToOwner(Generic[SessionRequest, Response]):
    """A single-session RPC, sent to the shard that owns the request's session."""

    def __init__(
        self,
        shards: Sequence[QueryStub],
        rpc: Callable[[QueryStub], UnaryRpc[SessionRequest, Response]],
    ) -> None:
        self._shards = shards
        self._rpc = rpc

    def __call__(self, request: SessionRequest, timeout: float | None = None) -> Response:
        shard = shard_of(request.session_id, len(self._shards))
        return self._rpc(self._shards[shard])(request, timeout)


class _ToOneShard(Generic[BatchRequest, Response]):
    """A raw batch RPC, sent to the one shard that owns all of its sessions."""

    def __init__(
        self,
        shards: Sequence[QueryStub],
        rpc: Callable[[QueryStub], UnaryRpc[BatchRequest, Response]],
        ids: Callable[[BatchRequest], Sequence[str]],
    ) -> None:
        self._shards = shards
        self._rpc = rpc
        self._ids = ids

    def __call__(self, request: BatchRequest, timeout: float | None = None) -> Response:
        owners = {shard_of(i, len(self._shards)) for i in self._ids(request)}
        if len(owners) > 1:
            raise InvalidArgument(
                f"expected the sessions of a raw batch on one shard, got shards "
                f"{sorted(owners)}; use a SessionBatch (create_batch) to split batches "
                "across shards",
                StatusCode.INVALID_ARGUMENT,
            )
        return self._rpc(self._shards[owners.pop() if owners else 0])(request, timeout)


def _step_ids(request: esa_pb2.StepStreamRequest) -> Sequence[str]:
    if request.WhichOneof("kind") == "report_batch":
        return request.report_batch.session_ids
    return request.probe_batch.session_ids


class ShardedStub:
    """The ``EsaServiceStub`` interface over N shards: each call goes to its session's shard.

    The raw wire API of :class:`~esa_client.ShardedEsaClient` (``client.stub``).
    ``CreateSession`` without an id gets a client-generated UUID (the shard must be
    known before the session exists). ``ProbeBatch`` / ``ReportBatch`` /
    ``StepStream`` are forwarded when all their sessions live on one shard; a batch
    spanning shards needs the action dimension to be split, so it goes through
    :class:`ShardedTransport` (what ``SessionBatch`` uses).
    """

    def __init__(self, shards: Sequence[QueryStub]) -> None:
        """Routes over ``shards``; ``shards[i]`` serves shard ``i``."""
        self.shards = tuple(shards)
        self.Probe = _ToOwner(self.shards, lambda s: s.Probe)
        self.Report = _ToOwner(self.shards, lambda s: s.Report)
        self.EndEpisode = _ToOwner(self.shards, lambda s: s.EndEpisode)
        self.CloseSession = _ToOwner(self.shards, lambda s: s.CloseSession)
        self.GetSession = _ToOwner(self.shards, lambda s: s.GetSession)
        self.ProbeBatch = _ToOneShard(self.shards, lambda s: s.ProbeBatch, lambda r: r.session_ids)
        self.ReportBatch = _ToOneShard(
            self.shards, lambda s: s.ReportBatch, lambda r: r.session_ids
        )
        self.StepStream = _ToOneShard(self.shards, lambda s: s.StepStream, _step_ids)

    def shard_of(self, session_id: str) -> int:
        """The shard that owns ``session_id``."""
        return shard_of(session_id, len(self.shards))

    def CreateSession(  # noqa: N802 (the RPC's name)
        self, request: esa_pb2.CreateSessionRequest, timeout: float | None = None
    ) -> esa_pb2.CreateSessionResponse:
        """Creates the session on its shard (an empty id: a UUID made here)."""
        if not request.session_id:
            request = esa_pb2.CreateSessionRequest(
                session_id=str(uuid.uuid4()), config=request.config
            )
        return self.shards[self.shard_of(request.session_id)].CreateSession(request, timeout)


class ShardedTransport:
    """The :class:`~esa_client.transports.base.Transport` over N shards, one transport each.

    Args:
        parts: ``parts[i]`` reaches shard ``i``; this transport owns and closes them.

    Attributes:
        parts: The per-shard transports.
    """

    def __init__(self, parts: Sequence[Transport]) -> None:
        """Routes over ``parts``; batches run their per-shard parts on one thread each."""
        if not parts:
            raise ValueError("expected at least one shard transport, got none")
        self.parts = tuple(parts)
        self._executor = ThreadPoolExecutor(max_workers=len(parts), thread_name_prefix="esa-shard")

    def shard_of(self, session_id: str) -> int:
        """The shard that owns ``session_id``."""
        return shard_of(session_id, len(self.parts))

    def _owner(self, session_id: str) -> Transport:
        return self.parts[self.shard_of(session_id)]

    def create_session(self, session_id: str, config: esa_pb2.SessionConfig) -> str:
        """Creates the session on its shard (an empty id: a UUID made here)."""
        session_id = session_id or str(uuid.uuid4())
        return self._owner(session_id).create_session(session_id, config)

    def get_session(self, session_id: str) -> SessionState:
        """Asks the session's shard."""
        return self._owner(session_id).get_session(session_id)

    def close_session(self, session_id: str) -> None:
        """Asks the session's shard."""
        self._owner(session_id).close_session(session_id)

    def end_episode(self, session_id: str) -> int:
        """Asks the session's shard."""
        return self._owner(session_id).end_episode(session_id)

    def probe(
        self,
        session_id: str,
        step: int,
        action: F64Array,
        episode_start: bool,
        action_scale: F64Array | None,
    ) -> tuple[F64Array, F64Array]:
        """Asks the session's shard."""
        owner = self._owner(session_id)
        return owner.probe(session_id, step, action, episode_start, action_scale)

    def report(
        self, session_id: str, step: int, q_value: float, q_reference: float | None
    ) -> F64Array:
        """Asks the session's shard."""
        return self._owner(session_id).report(session_id, step, q_value, q_reference)

    def open_batch(
        self, ids: Sequence[str], action_dim: int, *, use_stream: bool
    ) -> BatchTransport:
        """A :class:`ShardedBatch`: one sub-batch per shard that owns some of ``ids``."""
        return ShardedBatch(self.parts, ids, action_dim, self._executor, use_stream=use_stream)

    def healthy(self, timeout: float, *, wait_for_ready: bool = False) -> bool:
        """True if every shard answers (each within ``timeout`` seconds)."""
        return all(p.healthy(timeout, wait_for_ready=wait_for_ready) for p in self.parts)

    def close(self) -> None:
        """Stops the worker threads and closes every shard's transport."""
        self._executor.shutdown()
        for part in self.parts:
            part.close()


class ShardedBatch:
    """Splits each batch call per shard, sends the parts concurrently, merges answers in order.

    Args:
        parts: One transport per shard (``parts[i]`` reaches shard ``i``).
        ids: The batch's session ids, in batch order.
        action_dim: The batch's shared action dimension.
        executor: Runs the per-shard round trips concurrently.
        use_stream: Passed on to every shard's ``open_batch``.
    """

    def __init__(
        self,
        parts: Sequence[Transport],
        ids: Sequence[str],
        action_dim: int,
        executor: ThreadPoolExecutor,
        *,
        use_stream: bool,
    ) -> None:
        """Opens a sub-batch on every shard that owns some of ``ids``."""
        owner = np.array([shard_of(i, len(parts)) for i in ids], dtype=np.int64)
        self._items: dict[int, I64Array] = {
            s: np.flatnonzero(owner == s) for s in np.unique(owner).tolist()
        }
        self._batches = {
            s: parts[s].open_batch([ids[i] for i in items], action_dim, use_stream=use_stream)
            for s, items in self._items.items()
        }
        self._shape = (len(ids), action_dim)
        self._executor = executor

    def _scatter(self, send: Callable[[BatchTransport, I64Array], Answer]) -> dict[int, Answer]:
        """Runs ``send(shard's batch, its items)`` for every shard concurrently."""
        futures = {
            shard: self._executor.submit(send, batch, self._items[shard])
            for shard, batch in self._batches.items()
        }
        answers = {}
        for shard, future in futures.items():
            try:
                answers[shard] = future.result()
            except EsaError as err:
                raise _renumbered(err, self._items[shard], shard) from None
        return answers

    def _merged(self, parts: dict[int, F64Array]) -> F64Array:
        """The per-shard ``(k, D)`` values put back in batch order, ``(N, D)``."""
        merged = np.empty(self._shape, dtype=np.float64)
        for shard, values in parts.items():
            merged[self._items[shard]] = values
        return merged

    def probe(self, request: BatchProbe) -> tuple[F64Array, F64Array]:
        """Sends the per-shard probes concurrently; answers come back in batch order."""
        answers = self._scatter(lambda batch, items: batch.probe(_probe_part(request, items)))
        return self._probe_answer(answers)

    def report(self, request: BatchReport) -> F64Array:
        """Sends the per-shard reports concurrently; actions come back in batch order."""
        answers = self._scatter(lambda batch, items: batch.report(_report_part(request, items)))
        return self._merged(answers)

    def report_then_probe(
        self, report: BatchReport, probe: BatchProbe
    ) -> tuple[F64Array, F64Array]:
        """Each shard gets its part of both, pipelined on its batch; shards run concurrently."""
        answers = self._scatter(
            lambda batch, items: batch.report_then_probe(
                _report_part(report, items), _probe_part(probe, items)
            )
        )
        return self._probe_answer(answers)

    def _probe_answer(
        self, answers: dict[int, tuple[F64Array, F64Array]]
    ) -> tuple[F64Array, F64Array]:
        probes = self._merged({s: a[0] for s, a in answers.items()})
        return probes, self._merged({s: a[1] for s, a in answers.items()})

    def close(self) -> None:
        """Closes every per-shard batch."""
        for batch in self._batches.values():
            batch.close()


def _probe_part(request: BatchProbe, items: I64Array) -> BatchProbe:
    scales = request.action_scales
    return BatchProbe(
        request.steps[items],
        request.actions[items],
        request.episode_starts[items],
        None if scales is None else scales[items],
    )


def _report_part(request: BatchReport, items: I64Array) -> BatchReport:
    references = request.q_references
    return BatchReport(
        request.steps[items],
        request.q_values[items],
        None if references is None else references[items],
    )


def _renumbered(err: EsaError, items: I64Array, shard: int) -> EsaError:
    """The shard's error about its item k, as the error about item ``items[k]`` of the batch.

    The index comes from the error's data (``err.index``); the message, which the server
    starts with ``item k: `` for that same k, gets the batch's number instead, and the
    shard is named at the end.
    """
    message, index = err.message, None
    if err.index is not None and 0 <= err.index < len(items):
        index = int(items[err.index])
        message = f"item {index}: {message.removeprefix(f'item {err.index}: ')}"
    return type(err)(f"{message} (shard {shard})", err.code, index=index)
