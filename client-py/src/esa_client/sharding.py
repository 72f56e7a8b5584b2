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

Answer = TypeVar("Answer")

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

    def report_then_probe(
        self, report: esa_pb2.ReportBatchRequest, probe: esa_pb2.ProbeBatchRequest
    ) -> tuple[esa_pb2.ReportBatchResponse, esa_pb2.ProbeBatchResponse]:
        """A ReportBatch and the next ProbeBatch, pipelined where the transport can."""
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

    def _scatter(self, send: Callable[[BatchTransport, np.ndarray], Answer]) -> dict[int, Answer]:
        """Runs ``send(shard transport, its items)`` for every shard concurrently."""
        futures = {
            shard: self._executor.submit(send, self._parts[shard], items)
            for shard, items in self._items.items()
        }
        answers = {}
        for shard, future in futures.items():
            try:
                answers[shard] = future.result()
            except EsaError as err:
                raise _renumbered(err, self._items[shard], shard) from None
        return answers

    def _merged(self, n: int, parts: dict[int, Sequence[float]]) -> list[float]:
        """The per-shard ``(k, D)`` values put back in request order, flattened."""
        merged = np.empty((n, self._action_dim), dtype=np.float64)
        for shard, values in parts.items():
            merged[self._items[shard]] = np.asarray(values, dtype=np.float64).reshape(
                -1, self._action_dim
            )
        return merged.ravel().tolist()

    def _probe_part(
        self, request: esa_pb2.ProbeBatchRequest
    ) -> Callable[[np.ndarray], esa_pb2.ProbeBatchRequest]:
        actions = np.asarray(request.actions, dtype=np.float64).reshape(-1, self._action_dim)
        scales = np.asarray(request.action_scales, dtype=np.float64).reshape(-1, self._action_dim)
        starts = list(request.episode_starts)

        def part(items: np.ndarray) -> esa_pb2.ProbeBatchRequest:
            return esa_pb2.ProbeBatchRequest(
                session_ids=[request.session_ids[i] for i in items],
                steps=[request.steps[i] for i in items],
                actions=actions[items].ravel().tolist(),
                episode_starts=[starts[i] for i in items] if starts else [],
                action_scales=scales[items].ravel().tolist() if scales.size else [],
            )

        return part

    @staticmethod
    def _report_part(
        request: esa_pb2.ReportBatchRequest,
    ) -> Callable[[np.ndarray], esa_pb2.ReportBatchRequest]:
        references = list(request.q_references)

        def part(items: np.ndarray) -> esa_pb2.ReportBatchRequest:
            return esa_pb2.ReportBatchRequest(
                session_ids=[request.session_ids[i] for i in items],
                steps=[request.steps[i] for i in items],
                q_values=[request.q_values[i] for i in items],
                q_references=[references[i] for i in items] if references else [],
            )

        return part

    def _probe_answer(
        self, n: int, answers: dict[int, esa_pb2.ProbeBatchResponse]
    ) -> esa_pb2.ProbeBatchResponse:
        return esa_pb2.ProbeBatchResponse(
            probes=self._merged(n, {s: a.probes for s, a in answers.items()}),
            actions=self._merged(n, {s: a.actions for s, a in answers.items()}),
        )

    def _report_answer(
        self, n: int, answers: dict[int, esa_pb2.ReportBatchResponse]
    ) -> esa_pb2.ReportBatchResponse:
        return esa_pb2.ReportBatchResponse(
            actions=self._merged(n, {s: a.actions for s, a in answers.items()})
        )

    def probe_batch(self, request: esa_pb2.ProbeBatchRequest) -> esa_pb2.ProbeBatchResponse:
        """Sends the per-shard ProbeBatches concurrently; answers come back in request order."""
        part = self._probe_part(request)
        answers = self._scatter(lambda t, items: t.probe_batch(part(items)))
        return self._probe_answer(len(request.session_ids), answers)

    def report_batch(self, request: esa_pb2.ReportBatchRequest) -> esa_pb2.ReportBatchResponse:
        """Sends the per-shard ReportBatches concurrently; actions come back in request order."""
        part = self._report_part(request)
        answers = self._scatter(lambda t, items: t.report_batch(part(items)))
        return self._report_answer(len(request.session_ids), answers)

    def report_then_probe(
        self, report: esa_pb2.ReportBatchRequest, probe: esa_pb2.ProbeBatchRequest
    ) -> tuple[esa_pb2.ReportBatchResponse, esa_pb2.ProbeBatchResponse]:
        """Each shard gets its part of both, pipelined on its transport; shards run concurrently."""
        report_part, probe_part = self._report_part(report), self._probe_part(probe)
        pairs = self._scatter(
            lambda t, items: t.report_then_probe(report_part(items), probe_part(items))
        )
        n = len(probe.session_ids)
        return (
            self._report_answer(n, {s: pair[0] for s, pair in pairs.items()}),
            self._probe_answer(n, {s: pair[1] for s, pair in pairs.items()}),
        )

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
