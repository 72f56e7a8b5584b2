"""The esa contract over Zenoh queries (CONTRACT.md section 3).

Each RPC is a queryable at ``<prefix>/<RpcName>`` (default prefix ``esa/v1``): the
query payload is the protobuf request, a reply is the protobuf response, and a
reply error carries a ``StreamError`` (gRPC code number, message and failing batch
item). A server started with ``--auth-token-file`` wants the token as each query's
attachment. :class:`ZenohStub` mirrors the generated ``EsaServiceStub`` (one callable
per RPC, ``stub.Probe(request, timeout=...)``), so :class:`ZenohTransport` is the
message transport of :mod:`esa_client.transports.stub` over it.

Exactly one server serves a key, so a query that gets two replies means another
process answers for it too (a misconfigured deployment, or an impostor on an open
network): the call fails with :class:`TwoServersAnswered` instead of trusting either
answer. Queries go to every matching queryable, so an impostor cannot hide behind
being nearer than the real server.
"""

from __future__ import annotations

import contextlib
import json
import threading
from collections.abc import Sequence
from typing import Any, Generic, TypeVar

import zenoh
from google.protobuf.message import DecodeError, Message

from .._proto.esa.v1 import esa_pb2
from ..errors import DeadlineExceeded, EsaError, ServerUnavailable, StatusCode, esa_error
from .stub import StubTransport

DEFAULT_PREFIX = "esa/v1"

Response = TypeVar("Response", bound=Message)
Decoded = TypeVar("Decoded", bound=Message)


class TwoServersAnswered(EsaError):
    """More than one Zenoh peer answered one query, so neither answer can be trusted."""


# Response type of each RPC; StepStream answers one StepStreamRequest per query.
_RESPONSES: dict[str, type[Message]] = {
    "CreateSession": esa_pb2.CreateSessionResponse,
    "Probe": esa_pb2.ProbeResponse,
    "Report": esa_pb2.ReportResponse,
    "EndEpisode": esa_pb2.EndEpisodeResponse,
    "CloseSession": esa_pb2.CloseSessionResponse,
    "GetSession": esa_pb2.GetSessionResponse,
    "ProbeBatch": esa_pb2.ProbeBatchResponse,
    "ReportBatch": esa_pb2.ReportBatchResponse,
    "StepStream": esa_pb2.StepStreamResponse,
}


def check_prefix(prefix: str) -> str:
    """Returns ``prefix`` if it is a literal Zenoh key expression (as the server requires)."""
    chunks = prefix.split("/")
    if not prefix or any(not c or any(ch in c for ch in "*$?#") for c in chunks):
        raise ValueError(f"expected a key prefix without wildcards like 'esa/v1', got {prefix!r}")
    return prefix


def peer_config(connect: Sequence[str], timeout: float) -> zenoh.Config:
    """A Zenoh peer that only talks to ``connect``: no listener, no scouting, no gossip.

    Opening a session with it fails (instead of retrying forever) when an endpoint
    is not reachable within ``timeout`` seconds.
    """
    if not connect:
        raise ValueError("expected at least one Zenoh endpoint like 'tcp/127.0.0.1:7447', got []")
    config: zenoh.Config = zenoh.Config()
    for key, value in (
        ("mode", '"peer"'),
        ("connect/endpoints", json.dumps(list(connect))),
        ("connect/timeout_ms", str(max(1, round(timeout * 1000)))),
        ("connect/exit_on_failure", "true"),
        ("listen/endpoints", "[]"),
        ("scouting/multicast/enabled", "false"),
        ("scouting/gossip/enabled", "false"),
    ):
        config.insert_json5(key, value)
    return config


def open_session(config: zenoh.Config, where: str) -> zenoh.Session:
    """Opens a Zenoh session, raising ``ServerUnavailable`` (naming ``where``) on failure."""
    try:
        return zenoh.open(config)
    except zenoh.ZError as err:
        raise ServerUnavailable(
            f"cannot open a Zenoh session to {where}: {err}", StatusCode.UNAVAILABLE
        ) from None


class ZenohRpc(Generic[Response]):
    """One RPC of the contract as a Zenoh querier: ``rpc(request, timeout=...) -> response``."""

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        response: type[Response],
        timeout: float,
        token: str | None = None,
    ) -> None:
        """Declares the querier for ``key``; every query waits at most ``timeout`` seconds.

        Args:
            session: The Zenoh session.
            key: The RPC's key, e.g. ``esa/v1/Probe``.
            response: The response message type.
            timeout: Deadline of every query in seconds.
            token: The server's auth token, sent as each query's attachment.
        """
        self.key = key
        self._response = response
        self._timeout = timeout
        self._token = token
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

    def __call__(self, request: Message, timeout: float | None = None) -> Response:
        """Sends ``request`` and returns the decoded response.

        Args:
            request: The request message.
            timeout: Accepted for stub compatibility; the querier's deadline applies.

        Raises:
            EsaError: The server's error as its typed exception; ``ServerUnavailable``
                when no server serves the key; ``DeadlineExceeded`` when none answered in
                time; :class:`TwoServersAnswered` when more than one peer answered.
        """
        if not self.matched:
            raise self._unavailable()
        replies = self._querier.get(
            payload=request.SerializeToString(),
            encoding=zenoh.Encoding.APPLICATION_PROTOBUF,
            attachment=self._token,
        )
        # The query ends once every queryable of the key has answered: with one server,
        # right after its reply.
        answers = list(replies)
        if len(answers) > 1:
            repliers = ", ".join(str(reply.replier_id) for reply in answers)
            raise TwoServersAnswered(
                f"{self.key} was answered {len(answers)} times (by zenoh ids {repliers}): "
                "another process serves this key, so no answer is trusted; check the "
                "deployment's prefixes and access control (deploy/README.md)"
            )
        if not answers:
            # The query ended without a reply: the server went away while it was pending.
            raise self._unavailable()
        reply = answers[0]
        if reply.ok is not None:
            return self._decode(self._response, reply.ok.payload.to_bytes())
        raise self._error(reply.err)

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

    def _error(self, error: zenoh.ReplyError) -> EsaError:
        if error.encoding == zenoh.Encoding.APPLICATION_PROTOBUF:
            return esa_error(self._decode(esa_pb2.StreamError, error.payload.to_bytes()))
        # Errors the server did not write come from Zenoh itself; the one it sends
        # to a querier is its deadline ("Timeout").
        text = error.payload.to_string()
        if text == "Timeout":
            return DeadlineExceeded(
                f"no answer from {self.key} within {self._timeout} s",
                StatusCode.DEADLINE_EXCEEDED,
            )
        return EsaError(f"{self.key}: zenoh error {text!r}")

    def close(self) -> None:
        """Undeclares the querier."""
        self._querier.undeclare()


class ZenohStub:
    """The ``EsaServiceStub`` interface over Zenoh: one :class:`ZenohRpc` attribute per RPC.

    ``StepStream`` is a plain query here: one ``StepStreamRequest`` in, one
    ``StepStreamResponse`` (possibly carrying an in-band ``error``) out.

    Attributes:
        prefix: The key prefix, e.g. ``esa/v1`` or ``esa/v1/shard/1``.
    """

    CreateSession: ZenohRpc[esa_pb2.CreateSessionResponse]
    Probe: ZenohRpc[esa_pb2.ProbeResponse]
    Report: ZenohRpc[esa_pb2.ReportResponse]
    EndEpisode: ZenohRpc[esa_pb2.EndEpisodeResponse]
    CloseSession: ZenohRpc[esa_pb2.CloseSessionResponse]
    GetSession: ZenohRpc[esa_pb2.GetSessionResponse]
    ProbeBatch: ZenohRpc[esa_pb2.ProbeBatchResponse]
    ReportBatch: ZenohRpc[esa_pb2.ReportBatchResponse]
    StepStream: ZenohRpc[esa_pb2.StepStreamResponse]

    def __init__(
        self, session: zenoh.Session, prefix: str, timeout: float, token: str | None = None
    ) -> None:
        """Declares one querier per RPC under ``prefix`` on ``session``, sending ``token``."""
        self.prefix = check_prefix(prefix)
        self._rpcs = {
            name: ZenohRpc(session, f"{prefix}/{name}", response, timeout, token)
            for name, response in _RESPONSES.items()
        }
        for name, rpc in self._rpcs.items():
            setattr(self, name, rpc)

    def healthy(self, timeout: float, *, wait_for_ready: bool = False) -> bool:
        """True if the server behind this prefix answers a query within ``timeout`` seconds.

        Args:
            timeout: Bound on the whole check.
            wait_for_ready: Wait for the server's queryables to become reachable
                instead of failing at once when they are not (yet).
        """
        probe = self.GetSession
        if not (probe.wait_matched(timeout) if wait_for_ready else probe.matched):
            return False
        try:
            # An empty id is refused by every server: any answer proves it serves.
            probe(esa_pb2.GetSessionRequest())
        except (ServerUnavailable, DeadlineExceeded):
            return False
        except EsaError:
            return True
        return True

    def close(self) -> None:
        """Undeclares every querier."""
        for rpc in self._rpcs.values():
            rpc.close()


class ZenohStepQueries:
    """``StepStream`` messages as queries on the ``StepStream`` key, one per message.

    Zenoh queries are already message-oriented, so there is no stream to keep open:
    each message is one query whose answer may carry an in-band error.
    """

    def __init__(self, rpc: ZenohRpc[esa_pb2.StepStreamResponse]) -> None:
        """Sends through ``rpc`` (a stub's ``StepStream``)."""
        self._rpc = rpc

    def exchange(
        self, requests: Sequence[esa_pb2.StepStreamRequest]
    ) -> list[esa_pb2.StepStreamResponse]:
        """One query per request, in order."""
        return [self._rpc(request) for request in requests]

    def close(self) -> None:
        """Nothing to release."""


class ZenohTransport(StubTransport):
    """The :class:`~esa_client.transports.base.Transport` over Zenoh queries to one key prefix.

    Batches with ``use_stream=True`` send their messages to the ``StepStream`` key.

    Args:
        session: The Zenoh session (owned by the caller, who closes it after this).
        prefix: The key prefix, e.g. ``esa/v1`` or ``esa/v1/shard/1``.
        timeout: Deadline in seconds of every query.
        token: The server's auth token, sent as every query's attachment.

    Attributes:
        stub: The :class:`ZenohStub` under ``prefix``.
    """

    stub: ZenohStub

    def __init__(
        self, session: zenoh.Session, prefix: str, timeout: float, token: str | None = None
    ) -> None:
        """Declares the queriers of every RPC under ``prefix``."""
        stub = ZenohStub(session, prefix, timeout, token)
        super().__init__(stub, timeout, lambda: ZenohStepQueries(stub.StepStream))

    def healthy(self, timeout: float, *, wait_for_ready: bool = False) -> bool:
        """True if the server behind the prefix answers a query within ``timeout`` seconds."""
        return self.stub.healthy(timeout, wait_for_ready=wait_for_ready)

    def close(self) -> None:
        """Undeclares the queriers (nothing to do once the session is closed)."""
        with contextlib.suppress(zenoh.ZError):
            self.stub.close()
