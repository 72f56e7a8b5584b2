"""Spreading sessions over N ``esa-server`` processes (``--shard i/N``) by a stable hash.

Routing rule (the same in every client, see ``deploy/README.md``)::

    shard_of(id, N) = int.from_bytes(sha256(id.encode("utf-8")).digest()[:8], "big") % N

i.e. the first 8 bytes of the SHA-256 of the UTF-8 session id, read as a big-endian
unsigned 64-bit integer, modulo N. Shard ``i`` serves the keys ``<prefix>/shard/<i>/...``.

A session lives on exactly one shard, so single-session calls are forwarded as
they are. A batch is split into one sub-batch per shard, the sub-batches are sent
concurrently and the answers merged back into request order. Each sub-batch is
all-or-nothing on its shard; if one shard fails, the others may have applied
their part, and repeating the whole call is safe because a server treats a
repeated probe or report of the same step as a retry (CONTRACT.md).
"""

from __future__ import annotations

import hashlib
import re
import uuid
from collections.abc import Callable, Sequence
from concurrent.futures import Executor
from typing import Protocol, TypeVar

import grpc
import numpy as np
from google.protobuf.message import Message

from ._proto.esa.v1 import esa_pb2
from .errors import EsaError, InvalidArgument
from .zenoh_transport import ZenohRpc, ZenohStub

Batch = TypeVar("Batch", esa_pb2.ProbeBatchRequest, esa_pb2.ReportBatchRequest)
Answer = TypeVar("Answer", esa_pb2.ProbeBatchResponse, esa_pb2.ReportBatchResponse)

_ITEM = re.compile(r"^item (\d+): ")


def shard_of(session_id: str, shards: int) -> int:
    """The shard (0 <= shard < ``shards``) that owns ``session_id``; see the module docstring."""
    if shards < 1:
        raise ValueError(f"expected shards >= 1, got {shards}")
    digest = hashlib.sha256(session_id.encode("utf-8")).digest()
    return int.from_bytes(digest[:8], "big") % shards


def shard_prefix(prefix: str, shard: int) -> str:
    """The key prefix shard ``shard`` serves under ``prefix`` (``esa/v1/shard/1``)."""
    return f"{prefix}/shard/{shard}"


class BatchTransport(Protocol):
    """What a :class:`~esa_client.SessionBatch` sends its round trips through."""

    def probe_batch(self, request: esa_pb2.ProbeBatchRequest) -> esa_pb2.ProbeBatchResponse:
        """One ProbeBatch round trip."""
        ...

    def report_batch(self, request: esa_pb2.ReportBatchRequest) -> esa_pb2.ReportBatchResponse:
        """One ReportBatch round trip."""
        ...

    def close(self) -> None:
        """Releases the transport."""
        ...


class ShardedStub:
    """The ``EsaServiceStub`` interface over N shards: each call goes to its session's shard.

    ``CreateSession`` without an id gets a client-generated UUID (the shard must be
    known before the session exists). ``ProbeBatch`` / ``ReportBatch`` /
    ``StepStream`` are forwarded when all their sessions live on one shard; a batch
    spanning shards needs the action dimension to be split, so it goes through
    :class:`ShardedBatchTransport` (what ``SessionBatch`` uses).
    """

    def __init__(self, shards: Sequence[ZenohStub]) -> None:
        """Routes over ``shards``; ``shards[i]`` serves shard ``i``."""
        self.shards = tuple(shards)
        self.CreateSession = self._by_id(lambda s: s.CreateSession, create=True)
        for name in ("Probe", "Report", "EndEpisode", "CloseSession", "GetSession"):
            setattr(self, name, self._by_id(lambda s, name=name: getattr(s, name)))
        self.ProbeBatch = self._by_ids(lambda s: s.ProbeBatch, lambda r: r.session_ids)
        self.ReportBatch = self._by_ids(lambda s: s.ReportBatch, lambda r: r.session_ids)
        self.StepStream = self._by_ids(lambda s: s.StepStream, _step_ids)

    def shard_of(self, session_id: str) -> int:
        """The shard that owns ``session_id``."""
        return shard_of(session_id, len(self.shards))

    def _by_id(
        self, rpc: Callable[[ZenohStub], ZenohRpc], *, create: bool = False
    ) -> Callable[..., Message]:
        def forward(request: Message, timeout: float | None = None) -> Message:
            if create and not request.session_id:  # type: ignore[attr-defined]
                request = type(request)(session_id=str(uuid.uuid4()), config=request.config)  # type: ignore[attr-defined]
            shard = self.shard_of(request.session_id)  # type: ignore[attr-defined]
            return rpc(self.shards[shard])(request, timeout)

        return forward

    def _by_ids(
        self, rpc: Callable[[ZenohStub], ZenohRpc], ids: Callable[[Message], Sequence[str]]
    ) -> Callable[..., Message]:
        def forward(request: Message, timeout: float | None = None) -> Message:
            owners = {self.shard_of(i) for i in ids(request)}
            if len(owners) > 1:
                raise InvalidArgument(
                    f"expected the sessions of a raw batch on one shard, got shards "
                    f"{sorted(owners)}; use a SessionBatch (create_batch) to split batches "
                    "across shards",
                    grpc.StatusCode.INVALID_ARGUMENT,
                )
            return rpc(self.shards[owners.pop() if owners else 0])(request, timeout)

        return forward


def _step_ids(request: esa_pb2.StepStreamRequest) -> Sequence[str]:
    return getattr(request, request.WhichOneof("kind") or "probe_batch").session_ids


class ShardedBatchTransport:
    """Splits each batch per shard, sends the parts concurrently, merges answers in order.

    Args:
        parts: One transport per shard (``parts[i]`` talks to shard ``i``).
        ids: The batch's session ids, in batch order.
        action_dim: The batch's shared action dimension.
        executor: Runs the per-shard round trips concurrently.
    """

    def __init__(
        self,
        parts: Sequence[BatchTransport],
        ids: Sequence[str],
        action_dim: int,
        executor: Executor,
    ) -> None:
        """Precomputes which items each shard owns."""
        self._parts = tuple(parts)
        self._action_dim = action_dim
        self._executor = executor
        owner = np.array([shard_of(i, len(parts)) for i in ids], dtype=np.int64)
        self._items = {s: np.flatnonzero(owner == s) for s in np.unique(owner).tolist()}

    def _scatter(
        self,
        request: Batch,
        split: Callable[[Batch, np.ndarray], Batch],
        send: Callable[[BatchTransport, Batch], Answer],
        values: Callable[[Answer], Sequence[float]],
    ) -> np.ndarray:
        n = len(request.session_ids)
        futures = {
            shard: self._executor.submit(send, self._parts[shard], split(request, items))
            for shard, items in self._items.items()
        }
        merged = np.empty((n, self._action_dim), dtype=np.float64)
        for shard, future in futures.items():
            items = self._items[shard]
            try:
                answer = future.result()
            except EsaError as err:
                raise _renumbered(err, items, shard) from None
            part = np.asarray(values(answer), dtype=np.float64)
            merged[items] = part.reshape(-1, self._action_dim)
        return merged

    def probe_batch(self, request: esa_pb2.ProbeBatchRequest) -> esa_pb2.ProbeBatchResponse:
        """Sends the per-shard ProbeBatches concurrently; probes come back in request order."""
        actions = np.asarray(request.actions, dtype=np.float64).reshape(-1, self._action_dim)
        starts = list(request.episode_starts)

        def split(req: esa_pb2.ProbeBatchRequest, items: np.ndarray) -> esa_pb2.ProbeBatchRequest:
            return esa_pb2.ProbeBatchRequest(
                session_ids=[req.session_ids[i] for i in items],
                steps=[req.steps[i] for i in items],
                actions=actions[items].ravel().tolist(),
                episode_starts=[starts[i] for i in items] if starts else [],
            )

        merged = self._scatter(request, split, lambda t, r: t.probe_batch(r), lambda a: a.probes)
        return esa_pb2.ProbeBatchResponse(probes=merged.ravel().tolist())

    def report_batch(self, request: esa_pb2.ReportBatchRequest) -> esa_pb2.ReportBatchResponse:
        """Sends the per-shard ReportBatches concurrently; actions come back in request order."""

        def split(req: esa_pb2.ReportBatchRequest, items: np.ndarray) -> esa_pb2.ReportBatchRequest:
            return esa_pb2.ReportBatchRequest(
                session_ids=[req.session_ids[i] for i in items],
                steps=[req.steps[i] for i in items],
                q_values=[req.q_values[i] for i in items],
            )

        merged = self._scatter(request, split, lambda t, r: t.report_batch(r), lambda a: a.actions)
        return esa_pb2.ReportBatchResponse(actions=merged.ravel().tolist())

    def close(self) -> None:
        """Closes every per-shard transport."""
        for part in self._parts:
            part.close()


def _renumbered(err: EsaError, items: np.ndarray, shard: int) -> EsaError:
    """The shard's error, its ``item k`` renumbered to the position in the whole batch."""
    match = _ITEM.match(err.message)
    message = err.message
    if match and int(match.group(1)) < len(items):
        message = f"item {items[int(match.group(1))]}: {message[match.end() :]}"
    return type(err)(f"{message} (shard {shard})", err.code)
