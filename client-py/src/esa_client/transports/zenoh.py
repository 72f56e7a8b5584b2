"""The transport over Zenoh queries (CONTRACT.md section 3), to one server or N shards.

A batch is split per shard (docs/guides/server.md), each part all-or-nothing on its shard.
"""

from __future__ import annotations

import contextlib
import json
import threading
import uuid
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Generic, TypeVar

import numpy as np
import zenoh
from google.protobuf.message import DecodeError, Message

from .._proto.esa.v1 import esa_pb2
from ..errors import DeadlineExceeded, EsaError, ServerUnavailable, StatusCode, esa_error
from ..sharding import shard_of, shard_prefix
from ..state import F64Array, I64Array, SessionProgress, SessionState
from .base import BatchProbe, BatchReport, BatchTransport, SessionProbe

DEFAULT_PREFIX = "esa/v1"

Response = TypeVar("Response", bound=Message)
Decoded = TypeVar("Decoded", bound=Message)
Answer = TypeVar("Answer")
_Request = TypeVar("_Request", BatchProbe, BatchReport)


class TwoServersAnswered(EsaError):
    """More than one Zenoh peer answered one query, so neither answer can be trusted."""


def check_prefix(prefix: str) -> str:
    """Returns ``prefix`` if it is a literal Zenoh key expression (as the server requires)."""
    chunks = prefix.split("/")
    if not prefix or any(not c or any(ch in c for ch in "*$?#") for c in chunks):
        raise ValueError(f"expected a key prefix without wildcards like 'esa/v1', got {prefix!r}")
    return prefix


def check_shards(shards: int | None) -> int | None:
    """Returns ``shards`` if it is None (one server) or a count of servers >= 1."""
    if shards is not None and (
        isinstance(shards, bool) or not isinstance(shards, int) or shards < 1
    ):
        raise ValueError(f"expected shards >= 1 (or None for one server), got {shards!r}")
    return shards


def check_endpoints(connect: str | Sequence[str]) -> tuple[str, ...]:
    """``connect`` as a tuple of Zenoh endpoints (``tcp/127.0.0.1:7447``), checked."""
    endpoints = (connect,) if isinstance(connect, str) else tuple(connect)
    if not endpoints:
        raise ValueError("expected at least one Zenoh endpoint like 'tcp/127.0.0.1:7447', got []")
    for endpoint in endpoints:
        if not isinstance(endpoint, str) or "/" not in endpoint:
            raise ValueError(
                f"expected a Zenoh endpoint like 'tcp/127.0.0.1:7447', got {endpoint!r}"
            )
    return endpoints


def peer_config(connect: Sequence[str], timeout: float) -> zenoh.Config:
    """A Zenoh peer that only talks to ``connect`` and fails if it is not there in ``timeout``."""
    config: zenoh.Config = zenoh.Config()
    for key, value in (
        ("mode", '"peer"'),
        ("connect/endpoints", json.dumps(list(check_endpoints(connect)))),
        ("connect/timeout_ms", str(max(1, round(timeout * 1000)))),
        ("connect/exit_on_failure", "true"),
        ("listen/endpoints", "[]"),
        ("scouting/multicast/enabled", "false"),
        ("scouting/gossip/enabled", "false"),
    ):
        config.insert_json5(key, value)
    return config


class ZenohRpc(Generic[Response]):
    """One RPC of the contract (its ``key``, e.g. ``esa/v1/Probe``) as a Zenoh querier."""

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        response: type[Response],
        timeout: float,
        token: str | None = None,
    ) -> None:
        """Declares the querier for ``key``."""
        self.key, self._response, self._timeout, self._token = key, response, timeout, token
        # ALL: every queryable of the key gets the query, so a second answerer shows.
        # NONE: no consolidation, which would merge (and so hide) a second reply.
        self._querier = session.declare_querier(
            key,
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.QueryConsolidation(zenoh.ConsolidationMode.NONE),
            timeout=timeout,
        )

    @property
    def matched(self) -> bool:
        """True while a server's queryable for this key is reachable."""
        # A MatchingStatus, whatever zenoh's stub (which says bool) claims.
        status: Any = self._querier.matching_status
        return bool(status.matching)

    def wait_matched(self, timeout: float) -> bool:
        """Waits up to ``timeout`` seconds for a queryable; returns whether one is reachable."""
        ready = threading.Event()
        listener = self._querier.declare_matching_listener(
            lambda status: ready.set() if status.matching else None
        )
        try:
            return self.matched or ready.wait(timeout)
        finally:
            listener.undeclare()

    def __call__(self, request: Message) -> Response:
        """Sends ``request`` and returns the decoded response.

        Raises:
            EsaError: The server's typed error; ``ServerUnavailable`` if no server serves the
                key, ``DeadlineExceeded`` if none answered in time, or TwoServersAnswered.
        """
        if not self.matched:
            raise self._unavailable()
        replies = self._querier.get(
            payload=request.SerializeToString(),
            encoding=zenoh.Encoding.APPLICATION_PROTOBUF,
            attachment=self._token,
        )
        answers = list(replies)
        if len(answers) > 1:
            repliers = ", ".join(str(reply.replier_id) for reply in answers)
            raise TwoServersAnswered(
                f"{self.key} was answered {len(answers)} times (by zenoh ids {repliers}): "
                "another process serves this key, so no answer is trusted; check the "
                "deployment's prefixes and access control (deploy/README.md)"
            )
        if not answers:  # the server went away while the query was pending
            raise self._unavailable()
        reply = answers[0]
        if reply.ok is not None:
            return self._decode(self._response, reply.ok.payload.to_bytes())
        error: EsaError
        if reply.err.encoding == zenoh.Encoding.APPLICATION_PROTOBUF:
            error = esa_error(self._decode(esa_pb2.StreamError, reply.err.payload.to_bytes()))
        elif (text := reply.err.payload.to_string()) == "Timeout":
            # Not the server's error but Zenoh's own, which to a querier is its deadline.
            error = DeadlineExceeded(
                f"no answer from {self.key} within {self._timeout} s", StatusCode.DEADLINE_EXCEEDED
            )
        else:
            error = EsaError(f"{self.key}: zenoh error {text!r}")
        if isinstance(error, DeadlineExceeded) and not self.matched:
            # Each querier learns on its own that the server went, so a query can leave on a
            # dead route.
            raise self._unavailable() from None
        raise error

    def _unavailable(self) -> ServerUnavailable:
        return ServerUnavailable(
            f"no esa server serves {self.key} over Zenoh: it is not running, not connected, "
            "or serves another prefix or shard",
            StatusCode.UNAVAILABLE,
        )

    def _decode(self, message_type: type[Decoded], data: bytes) -> Decoded:
        try:
            return message_type.FromString(data)
        except DecodeError as err:
            raise EsaError(
                f"{self.key} answered with bytes that are not a {message_type.__name__}: {err}"
            ) from None

    def close(self) -> None:
        """Undeclares the querier."""
        self._querier.undeclare()


class _Server:
    """The queriers of one server's key prefix (``esa/v1``, ``esa/v1/shard/1``), one per RPC."""

    def __init__(
        self, session: zenoh.Session, prefix: str, timeout: float, token: str | None
    ) -> None:
        def rpc(name: str, response: type[Response]) -> ZenohRpc[Response]:
            return ZenohRpc(session, f"{prefix}/{name}", response, timeout, token)

        self.create_session = rpc("CreateSession", esa_pb2.CreateSessionResponse)
        self.get_session = rpc("GetSession", esa_pb2.GetSessionResponse)
        self.close_session = rpc("CloseSession", esa_pb2.CloseSessionResponse)
        self.end_episode = rpc("EndEpisode", esa_pb2.EndEpisodeResponse)
        self.probe = rpc("Probe", esa_pb2.ProbeResponse)
        self.report = rpc("Report", esa_pb2.ReportResponse)
        self.probe_batch = rpc("ProbeBatch", esa_pb2.ProbeBatchResponse)
        self.report_batch = rpc("ReportBatch", esa_pb2.ReportBatchResponse)

    def healthy(self, timeout: float, *, wait_for_ready: bool) -> bool:
        """True if the server behind this prefix answers a query within ``timeout`` seconds."""
        probe = self.get_session
        if not (probe.wait_matched(timeout) if wait_for_ready else probe.matched):
            return False
        try:
            # An empty id is refused by every server: any answer proves it serves.
            probe(esa_pb2.GetSessionRequest())
        except EsaError as err:
            return not isinstance(err, (ServerUnavailable, DeadlineExceeded))
        return True

    def close(self) -> None:
        for rpc in list(vars(self).values()):
            if isinstance(rpc, ZenohRpc):
                rpc.close()


class ZenohTransport:
    """The Transport over Zenoh to one server or N shards; :meth:`open` builds it.

    ``session`` is closed by :meth:`close`; ``timeout`` is each query's deadline in seconds;
    ``shards``: N servers started with ``--shard i/N``, None for one server.
    """

    def __init__(
        self,
        session: zenoh.Session,
        prefix: str,
        timeout: float,
        token: str | None = None,
        shards: int | None = None,
    ) -> None:
        """Declares the queriers of every RPC of every server."""
        self.prefix = check_prefix(prefix)
        self.shards = check_shards(shards)
        prefixes = [prefix] if shards is None else [shard_prefix(prefix, i) for i in range(shards)]
        self._session = session
        self._servers = [_Server(session, p, timeout, token) for p in prefixes]
        # Threads start on a sharded batch's first call only.
        self._executor = ThreadPoolExecutor(len(prefixes), thread_name_prefix="esa-shard")

    @classmethod
    def open(
        cls,
        connect: str | Sequence[str],
        *,
        prefix: str,
        timeout: float,
        token: str | None,
        shards: int | None,
        config: zenoh.Config | None,
    ) -> ZenohTransport:
        """Opens a Zenoh session to ``connect`` (or with ``config``) and the transport on it.

        ``timeout`` is also the deadline of connecting.

        Raises:
            ValueError: A malformed endpoint, prefix or shard count.
            ServerUnavailable: If the session cannot be opened.
        """
        where = ",".join(check_endpoints(connect))
        check_prefix(prefix)
        check_shards(shards)
        try:
            session = zenoh.open(config if config is not None else peer_config(connect, timeout))
        except zenoh.ZError as err:
            raise ServerUnavailable(
                f"cannot open a Zenoh session to {where}: {err}", StatusCode.UNAVAILABLE
            ) from None
        try:
            return cls(session, prefix, timeout, token, shards)
        except BaseException:
            with contextlib.suppress(zenoh.ZError):
                session.close()
            raise

    def shard_of(self, session_id: str) -> int:
        """The shard that owns ``session_id`` (0 for one server)."""
        return shard_of(session_id, len(self._servers))

    def _owner(self, session_id: str) -> _Server:
        return self._servers[self.shard_of(session_id)]

    def create_session(self, session_id: str, config: esa_pb2.SessionConfig) -> str:
        """``CreateSession`` on the session's shard (an empty id: a UUID, made here if sharded)."""
        if self.shards is not None:  # the shard must be known before the session exists
            session_id = session_id or str(uuid.uuid4())
        request = esa_pb2.CreateSessionRequest(session_id=session_id, config=config)
        return self._owner(session_id).create_session(request).session_id

    def resume_session(
        self, session_id: str, config: esa_pb2.SessionConfig, progress: esa_pb2.SessionProgress
    ) -> str:
        """``CreateSession`` of a lost session on its shard, resuming its ``progress``."""
        request = esa_pb2.CreateSessionRequest(
            session_id=session_id, config=config, progress=progress
        )
        return self._owner(session_id).create_session(request).session_id

    def get_session(self, session_id: str) -> SessionState:
        """``GetSession``."""
        request = esa_pb2.GetSessionRequest(session_id=session_id)
        return SessionState.from_proto(self._owner(session_id).get_session(request))

    def close_session(self, session_id: str) -> None:
        """``CloseSession``."""
        self._owner(session_id).close_session(esa_pb2.CloseSessionRequest(session_id=session_id))

    def end_episode(self, session_id: str) -> int:
        """``EndEpisode``; returns the completed-episode count."""
        request = esa_pb2.EndEpisodeRequest(session_id=session_id)
        return self._owner(session_id).end_episode(request).episodes_completed

    def probe(self, probe: SessionProbe) -> tuple[F64Array, F64Array]:
        """``Probe``; returns the probe and the applied action."""
        session_id, action_scale = probe.session_id, probe.action_scale
        request = esa_pb2.ProbeRequest(
            session_id=session_id,
            step=probe.step,
            action=probe.action.tolist(),
            episode_start=probe.episode_start,
            action_scale=[] if action_scale is None else action_scale.tolist(),
        )
        response = self._owner(session_id).probe(request)
        return _f64(response.probe), _f64(response.action)

    def report(
        self, session_id: str, step: int, q_value: float, q_reference: float | None
    ) -> F64Array:
        """``Report``; returns the improved action."""
        request = esa_pb2.ReportRequest(session_id=session_id, step=step, q_value=q_value)
        if q_reference is not None:
            request.q_reference = q_reference
        return _f64(self._owner(session_id).report(request).action)

    def open_batch(
        self, ids: Sequence[str], action_dim: int, *, use_stream: bool
    ) -> BatchTransport:
        """The batch's queries (each already one message: no stream), split over its shards."""
        owner = np.array([self.shard_of(i) for i in ids], dtype=np.int64)
        parts = {s: np.flatnonzero(owner == s) for s in np.unique(owner).tolist()}
        if len(parts) <= 1:
            return _ServerBatch(self._servers[next(iter(parts), 0)], ids, action_dim)
        batches = {
            s: (items, _ServerBatch(self._servers[s], [ids[i] for i in items.tolist()], action_dim))
            for s, items in parts.items()
        }
        return _ShardedBatch(batches, (len(ids), action_dim), self._executor)

    def healthy(self, timeout: float, *, wait_for_ready: bool = False) -> bool:
        """True if every server answers (each within ``timeout`` seconds)."""
        return all(s.healthy(timeout, wait_for_ready=wait_for_ready) for s in self._servers)

    def close(self) -> None:
        """Undeclares the queriers and closes the Zenoh session. Idempotent."""
        self._executor.shutdown()
        with contextlib.suppress(zenoh.ZError):
            for server in self._servers:
                server.close()
            self._session.close()

    def __repr__(self) -> str:
        """Shows the prefix and shard count."""
        shards = "" if self.shards is None else f", shards={self.shards}"
        return f"ZenohTransport(prefix={self.prefix!r}{shards})"


class _ServerBatch(BatchTransport):
    """A batch's round trips to one server as ``ProbeBatch`` / ``ReportBatch`` queries."""

    def __init__(self, server: _Server, ids: Sequence[str], action_dim: int) -> None:
        self._server = server
        self._ids = tuple(ids)
        self._shape = (len(self._ids), action_dim)
        self._seen: esa_pb2.ProbeBatchResponse | None = None  # the last probe's answer

    def progress(self) -> list[SessionProgress] | None:
        seen = self._seen
        if seen is None or len(seen.episodes_completed) != len(self._ids):
            return None
        return SessionProgress.from_batch_answer(
            seen.episodes_completed, seen.response_mean_squares
        )

    def _values(self, values: Sequence[float]) -> F64Array:
        return _f64(values).reshape(self._shape)

    def probe(self, request: BatchProbe) -> tuple[F64Array, F64Array]:
        scales = request.action_scales
        message = esa_pb2.ProbeBatchRequest(
            session_ids=self._ids,
            steps=request.steps.tolist(),
            actions=request.actions.ravel().tolist(),
            episode_starts=request.episode_starts.tolist(),
            action_scales=[] if scales is None else scales.ravel().tolist(),
        )
        response = self._server.probe_batch(message)
        self._seen = response
        return self._values(response.probes), self._values(response.actions)

    def report(self, request: BatchReport) -> F64Array:
        references = request.q_references
        message = esa_pb2.ReportBatchRequest(
            session_ids=self._ids,
            steps=request.steps.tolist(),
            q_values=request.q_values.tolist(),
            q_references=[] if references is None else references.tolist(),
        )
        return self._values(self._server.report_batch(message).actions)


class _ShardedBatch(BatchTransport):
    """Splits each batch call per shard, sends the parts concurrently, merges answers in order."""

    def __init__(
        self,
        parts: dict[int, tuple[I64Array, _ServerBatch]],
        shape: tuple[int, int],
        executor: ThreadPoolExecutor,
    ) -> None:
        self._parts, self._shape, self._executor = parts, shape, executor

    def _scatter(self, send: Callable[[_ServerBatch, I64Array], Answer]) -> dict[int, Answer]:
        """Runs ``send(shard's batch, its items)`` for every shard concurrently."""
        futures = {
            shard: self._executor.submit(send, batch, items)
            for shard, (items, batch) in self._parts.items()
        }
        answers = {}
        for shard, future in futures.items():
            try:
                answers[shard] = future.result()
            except EsaError as err:
                raise _renumbered(err, self._parts[shard][0], shard) from None
        return answers

    def _merged(self, parts: dict[int, F64Array]) -> F64Array:
        """The per-shard ``(k, D)`` values in batch order, ``(N, D)``."""
        merged = np.empty(self._shape, dtype=np.float64)
        for shard, values in parts.items():
            merged[self._parts[shard][0]] = values
        return merged

    def probe(self, request: BatchProbe) -> tuple[F64Array, F64Array]:
        answers = self._scatter(lambda batch, items: batch.probe(_part(request, items)))
        probes = self._merged({s: a[0] for s, a in answers.items()})
        return probes, self._merged({s: a[1] for s, a in answers.items()})

    def report(self, request: BatchReport) -> F64Array:
        return self._merged(self._scatter(lambda batch, items: batch.report(_part(request, items))))

    def progress(self) -> list[SessionProgress] | None:
        merged: list[SessionProgress | None] = [None] * self._shape[0]
        for items, batch in self._parts.values():
            part = batch.progress()
            if part is None:
                return None
            for item, progress in zip(items.tolist(), part, strict=True):
                merged[item] = progress
        return [p for p in merged if p is not None]


def _f64(values: Sequence[float]) -> F64Array:
    return np.array(values, dtype=np.float64)


def _part(request: _Request, items: I64Array) -> _Request:
    """The rows ``items`` of every array of ``request`` (None stays None)."""
    rows: list[Any] = [None if array is None else array[items] for array in request]
    return type(request)(*rows)


def _renumbered(err: EsaError, items: I64Array, shard: int) -> EsaError:
    """The shard's error about its item k (``err.index``), as the error about ``items[k]``."""
    message, index = err.message, None
    if err.index is not None and 0 <= err.index < len(items):
        index = int(items[err.index])
        message = f"item {index}: {message.removeprefix(f'item {err.index}: ')}"
    return type(err)(f"{message} (shard {shard})", err.code, index=index)
