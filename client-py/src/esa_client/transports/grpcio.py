"""The transport over gRPC: a channel to one server, unary calls and one StepStream per batch.

Every wait is bounded by the transport's timeout and every failure becomes an
:class:`~esa_client.errors.EsaError`. A batch with ``use_stream=True`` gets its own
bidirectional ``StepStream``: the pipelined step of CONTRACT.md section 1b sends the
report and the next probe before reading either answer, so a step costs one round trip.
"""

from __future__ import annotations

import collections
import os
import queue
import threading
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import grpc
from grpc_health.v1 import health_pb2, health_pb2_grpc

from .._proto.esa.v1 import esa_pb2, esa_pb2_grpc
from ..errors import DeadlineExceeded, EsaError, ServerUnavailable, StatusCode
from .stub import StubTransport, rpc_error

_CHANNEL_OPTIONS: list[tuple[str, int | str]] = [
    # The server is local: never route through an HTTP proxy from the environment.
    ("grpc.enable_http_proxy", 0),
    # Reconnect quickly after a restart instead of gRPC's default 1 s backoff start.
    ("grpc.initial_reconnect_backoff_ms", 100),
    ("grpc.min_reconnect_backoff_ms", 100),
    ("grpc.max_reconnect_backoff_ms", 2000),
    ("grpc.max_receive_message_length", 256 * 1024 * 1024),
    ("grpc.max_send_message_length", 256 * 1024 * 1024),
]


@dataclass(frozen=True)
class TlsConfig:
    """TLS for the channel to a server started with ``--tls-cert`` and ``--tls-key``.

    Connect to a host name (or IP address) that the server's certificate names; a failed
    handshake (untrusted server, refused client certificate) raises ``ServerUnavailable``.

    Args:
        ca: PEM file of the CA(s) that issued the server's certificate; None trusts the
            system's roots.
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

    def credentials(self) -> grpc.ChannelCredentials:
        """The channel credentials, the files read now.

        Raises:
            OSError: If a file cannot be read.
        """

        def read(path: str | os.PathLike[str] | None) -> bytes | None:
            return None if path is None else Path(path).read_bytes()

        return grpc.ssl_channel_credentials(
            root_certificates=read(self.ca),
            private_key=read(self.key),
            certificate_chain=read(self.cert),
        )


_CallFields = collections.namedtuple(
    "_CallFields",
    ["method", "timeout", "metadata", "credentials", "wait_for_ready", "compression"],
)


class _CallDetails(_CallFields, grpc.ClientCallDetails):
    """A call's details with changed fields (gRPC's own type cannot be constructed)."""


class _BearerToken(grpc.UnaryUnaryClientInterceptor, grpc.StreamStreamClientInterceptor):
    """Adds ``authorization: Bearer <token>`` to every call (the server's ``--auth-token-file``)."""

    def __init__(self, token: str) -> None:
        """Sends ``token`` with every call."""
        self._metadata = (("authorization", f"Bearer {token}"),)

    def _with_token(self, details: grpc.ClientCallDetails) -> _CallDetails:
        return _CallDetails(
            details.method,
            details.timeout,
            (*(details.metadata or ()), *self._metadata),
            details.credentials,
            details.wait_for_ready,
            details.compression,
        )

    def intercept_unary_unary(
        self, continuation: Callable[..., Any], details: grpc.ClientCallDetails, request: Any
    ) -> Any:
        """Sends a unary call with the token."""
        return continuation(self._with_token(details), request)

    def intercept_stream_stream(
        self,
        continuation: Callable[..., Any],
        details: grpc.ClientCallDetails,
        request_iterator: Iterator[Any],
    ) -> Any:
        """Opens a stream with the token."""
        return continuation(self._with_token(details), request_iterator)


_END = object()


class GrpcStepStream:
    """One long-lived ``StepStream``: the :class:`~esa_client.transports.stub.StepExchange` of gRPC.

    gRPC's blocking stream iterator has no per-message deadline, so a reader thread
    moves responses into a queue that the caller waits on with the timeout. After a
    timeout or a transport failure the stream is out of step with its requests, so
    it is dropped and the next call opens a new one; that is safe because the
    server accepts a repeated probe or report for the same step (CONTRACT.md).
    """

    def __init__(self, open_stream: Callable[[Iterator[object]], Any], timeout: float) -> None:
        """Prepares the exchange; the stream (``open_stream(requests)``) opens on first use."""
        self._open_stream = open_stream
        self._timeout = timeout
        self._requests: queue.SimpleQueue[object] = queue.SimpleQueue()
        self._responses: queue.SimpleQueue[object] = queue.SimpleQueue()
        self._call: Any = None

    def _open(self) -> None:
        requests: queue.SimpleQueue[object] = queue.SimpleQueue()
        responses: queue.SimpleQueue[object] = queue.SimpleQueue()
        stream = self._open_stream(iter(requests.get, _END))

        def read() -> None:
            try:
                for response in stream:
                    responses.put(response)
                responses.put(
                    ServerUnavailable("the server closed the StepStream", StatusCode.UNAVAILABLE)
                )
            except grpc.RpcError as err:
                responses.put(rpc_error(err))

        threading.Thread(target=read, name="esa-step-stream", daemon=True).start()
        self._requests, self._responses, self._call = requests, responses, stream

    def _drop(self) -> None:
        if self._call is not None:
            self._call.cancel()
            # Unblocks gRPC's request-consuming thread, which waits on this queue.
            self._requests.put(_END)
        self._call = None

    def exchange(
        self, requests: Sequence[esa_pb2.StepStreamRequest]
    ) -> list[esa_pb2.StepStreamResponse]:
        """Writes every request before reading: one round trip for all of them."""
        if self._call is None:
            self._open()
        for request in requests:
            self._requests.put(request)
        answers: list[esa_pb2.StepStreamResponse] = []
        for _ in requests:
            try:
                item = self._responses.get(timeout=self._timeout)
            except queue.Empty:
                self._drop()
                raise DeadlineExceeded(
                    f"no StepStream response within {self._timeout} s",
                    StatusCode.DEADLINE_EXCEEDED,
                ) from None
            if isinstance(item, EsaError):
                self._drop()
                raise item
            assert isinstance(item, esa_pb2.StepStreamResponse)  # all else the reader puts
            answers.append(item)
        return answers

    def close(self) -> None:
        """Ends the stream."""
        self._drop()


class GrpcTransport(StubTransport):
    """The :class:`~esa_client.transports.base.Transport` over a gRPC channel to one server.

    Args:
        address: ``host:port`` or ``unix:/path/to/socket`` (checked by the caller).
        timeout: Deadline in seconds of every call.
        token: Sent as ``authorization: Bearer <token>`` with every call; None sends none.
        tls: Connect over TLS; None connects in plaintext.

    Attributes:
        channel: The gRPC channel (connecting lazily).
        stub: The generated ``EsaServiceStub`` on it.
    """

    def __init__(
        self,
        address: str,
        timeout: float,
        token: str | None = None,
        tls: TlsConfig | None = None,
    ) -> None:
        """Opens the channel (connecting lazily)."""
        options = list(_CHANNEL_OPTIONS)
        if address.startswith("unix:"):
            # gRPC core would send the socket path as :authority, which HTTP/2 servers
            # such as hyper (tonic) reject as malformed; any valid host name works.
            options.append(("grpc.default_authority", "localhost"))
        channel: grpc.Channel
        if tls is not None:
            if tls.server_name is not None:
                options.append(("grpc.ssl_target_name_override", tls.server_name))
            credentials = tls.credentials()
            if token is not None:
                # gRPC sends call credentials only over TLS, as the same Bearer header.
                credentials = grpc.composite_channel_credentials(
                    credentials, grpc.access_token_call_credentials(token)
                )
            self.channel = grpc.secure_channel(address, credentials, options=options)
            channel = self.channel
        else:
            self.channel = grpc.insecure_channel(address, options=options)
            # Only with a token: an interceptor costs every call some microseconds.
            channel = (
                self.channel
                if token is None
                else grpc.intercept_channel(self.channel, _BearerToken(token))
            )
        stub = esa_pb2_grpc.EsaServiceStub(channel)
        self._health = health_pb2_grpc.HealthStub(channel)
        super().__init__(stub, timeout, lambda: GrpcStepStream(stub.StepStream, timeout))

    def healthy(self, timeout: float, *, wait_for_ready: bool = False) -> bool:
        """Asks the server's ``grpc.health.v1.Health`` service whether it is serving.

        Args:
            timeout: Deadline in seconds.
            wait_for_ready: Wait (up to the deadline) for the connection instead of
                failing at once when the server is not reachable yet.
        """
        try:
            response = self._health.Check(
                health_pb2.HealthCheckRequest(service=""),
                timeout=timeout,
                wait_for_ready=wait_for_ready,
            )
        except grpc.RpcError:
            return False
        serving: bool = response.status == health_pb2.HealthCheckResponse.SERVING
        return serving

    def close(self) -> None:
        """Closes the channel (and with it every open StepStream)."""
        self.channel.close()
