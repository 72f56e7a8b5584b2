"""``EsaClient``: a connection to an esa server, optionally one it starts itself."""

from __future__ import annotations

import collections
import contextlib
import os
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import grpc
from grpc_health.v1 import health_pb2, health_pb2_grpc

from ._proto.esa.v1 import esa_pb2, esa_pb2_grpc
from .config import SessionConfig
from .errors import EsaError, ServerUnavailable, SessionNotFound
from .session import Session, SessionBatch, SessionState, as_batch_configs
from .sidecar import ServerProcess
from .transport import StreamTransport, UnaryTransport, call

if TYPE_CHECKING:
    from .sharding import BatchTransport

_CHANNEL_OPTIONS = [
    # The server is local: never route through an HTTP proxy from the environment.
    ("grpc.enable_http_proxy", 0),
    # Reconnect quickly after a restart instead of gRPC's default 1 s backoff start.
    ("grpc.initial_reconnect_backoff_ms", 100),
    ("grpc.min_reconnect_backoff_ms", 100),
    ("grpc.max_reconnect_backoff_ms", 2000),
    ("grpc.max_receive_message_length", 256 * 1024 * 1024),
    ("grpc.max_send_message_length", 256 * 1024 * 1024),
]


def _check_address(address: str) -> str:
    if address.startswith("unix:"):
        if len(address) <= len("unix:"):
            raise ValueError(f"expected 'unix:/path/to/socket', got {address!r}")
        return address
    host, sep, port = address.rpartition(":")
    if not sep or not host or not port.isdigit():
        raise ValueError(f"expected 'host:port' or 'unix:/path', got {address!r}")
    return address


TOKEN_ENV = "ESA_AUTH_TOKEN"


def resolve_token(token: str | None, token_file: str | os.PathLike[str] | None) -> str | None:
    """The auth token to send: ``token``, else ``token_file``'s content, else ``$ESA_AUTH_TOKEN``.

    Surrounding whitespace is removed, as the server does with its ``--auth-token-file``.

    Raises:
        ValueError: If both are given, or the token found is empty.
        OSError: If ``token_file`` cannot be read.
    """
    if token is not None and token_file is not None:
        raise ValueError(f"expected token or token_file, got both (token_file={token_file!r})")
    source = "token"
    if token_file is not None:
        token, source = Path(token_file).read_text(), f"token_file {token_file}"
    elif token is None:
        token, source = os.environ.get(TOKEN_ENV), f"${TOKEN_ENV}"
    if token is None:
        return None
    if not token.strip():
        raise ValueError(f"expected a non-empty auth token in {source}, got {token!r}")
    return token.strip()


_CALL_FIELDS = ("method", "timeout", "metadata", "credentials", "wait_for_ready", "compression")


class _CallDetails(collections.namedtuple("_CallDetails", _CALL_FIELDS), grpc.ClientCallDetails):
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


_Client = TypeVar("_Client", bound="EsaClient")


def connect_spawned(
    server: ServerProcess, connect: Callable[[], _Client], startup_timeout: float
) -> _Client:
    """Returns ``connect()``'s client once ``server`` is healthy; the client then owns it.

    What every ``spawn`` does after starting its server: if connecting or waiting
    fails, the server is stopped before the error propagates, so no child process
    outlives a failed ``spawn``.
    """
    try:
        client = connect()
        client.server = server
        client._wait_healthy(startup_timeout, server)
    except BaseException:
        server.stop()
        raise
    return client


class EsaClient:
    """A connection to an esa server.

    Every call has a deadline of ``timeout`` seconds; a lost connection raises
    :class:`~esa_client.errors.ServerUnavailable` at once instead of waiting.

    Example::

        with EsaClient.spawn() as client:
            session = client.create_session(SessionConfig(1, 0.05, 0.2, 10.0, 0.1))
            probe = session.probe([0.3], episode_start=True)
            action = session.report(q_value=critic(obs, probe))

    Args:
        address: ``host:port`` or ``unix:/path/to/socket``.
        timeout: Deadline in seconds for every call.
        token: The auth token of a server started with ``--auth-token-file``, sent as
            ``authorization: Bearer <token>`` metadata with every call.
        token_file: A file holding the token instead (e.g. the server's own token file).
            With neither, the ``ESA_AUTH_TOKEN`` environment variable is used if set.

    Attributes:
        address: The gRPC target.
        timeout: The per-call deadline in seconds.
        stub: The generated ``EsaServiceStub`` (for raw access to the wire API).
        server: The :class:`~esa_client.sidecar.ServerProcess` when started by
            :meth:`spawn`, else None.
        sessions_restored: How many sessions :meth:`restore_sessions` recreated.
    """

    def __init__(
        self,
        address: str = "127.0.0.1:50051",
        *,
        timeout: float = 5.0,
        token: str | None = None,
        token_file: str | os.PathLike[str] | None = None,
    ) -> None:
        """Opens a channel to ``address`` (connecting lazily)."""
        if not timeout > 0:
            raise ValueError(f"expected timeout > 0 seconds, got {timeout}")
        self.address = _check_address(address)
        self.timeout = float(timeout)
        resolved = resolve_token(token, token_file)
        options = list(_CHANNEL_OPTIONS)
        if self.address.startswith("unix:"):
            # gRPC core would send the socket path as :authority, which HTTP/2 servers
            # such as hyper (tonic) reject as malformed; any valid host name works.
            options.append(("grpc.default_authority", "localhost"))
        self._channel = grpc.insecure_channel(self.address, options=options)
        # Only with a token: an interceptor costs every call some microseconds.
        channel = (
            self._channel
            if resolved is None
            else grpc.intercept_channel(self._channel, _BearerToken(resolved))
        )
        self.stub = esa_pb2_grpc.EsaServiceStub(channel)
        self._health = health_pb2_grpc.HealthStub(channel)
        self.server: ServerProcess | None = None
        self.sessions_restored = 0
        self._closed = False

    @classmethod
    def spawn(
        cls,
        binary: str | os.PathLike[str] | None = None,
        *,
        session_ttl: float | None = None,
        max_sessions: int | None = None,
        max_session_memory: int | None = None,
        extra_args: Sequence[str] = (),
        timeout: float = 5.0,
        startup_timeout: float = 30.0,
    ) -> EsaClient:
        """Starts a private esa-server on a Unix socket and returns a client connected to it.

        The server is found via ``binary``, ``ESA_SERVER_BIN``, ``PATH`` or a cargo
        build of this repository (see :func:`esa_client.sidecar.find_server_binary`),
        and stopped by :meth:`close` (or at interpreter exit at the latest); if this
        process dies first, whatever the signal, the server stops by itself.

        Args:
            binary: Path of the esa-server executable; None searches for it.
            session_ttl: Idle-session expiry in seconds (0 = never); None = the server's
                default (600).
            max_sessions: Live-session limit; None = the server's default (100,000).
            max_session_memory: Session memory budget in bytes; None = the server's
                default (half of the memory it may use).
            extra_args: Further server arguments.
            timeout: Per-call deadline of the returned client.
            startup_timeout: Seconds to wait for the server to report healthy.

        Raises:
            ValueError: If a limit is not a number at least its minimum.
            EsaError: If the binary cannot be found or built.
            ServerUnavailable: If the server exits or is not healthy in time (with its output).
        """
        server = ServerProcess(
            binary,
            session_ttl=session_ttl,
            max_sessions=max_sessions,
            max_session_memory=max_session_memory,
            extra_args=extra_args,
        )
        return connect_spawned(
            server, lambda: cls(server.address, timeout=timeout), startup_timeout
        )

    def _wait_healthy(self, timeout: float, server: ServerProcess | None) -> None:
        deadline = time.monotonic() + timeout
        while True:
            if server is not None:
                server.check_running()
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                tail = f"; server output:\n{server.output_tail()}" if server else ""
                raise ServerUnavailable(
                    f"esa server at {self.address} not healthy within {timeout} s{tail}",
                    grpc.StatusCode.UNAVAILABLE,
                )
            # Short waits so that a crashed server process is noticed promptly.
            if self.healthy(timeout=min(0.25, remaining), wait_for_ready=True):
                return

    def healthy(self, *, timeout: float | None = None, wait_for_ready: bool = False) -> bool:
        """Asks the server's ``grpc.health.v1.Health`` service whether it is serving.

        Args:
            timeout: Deadline in seconds (default: the client's timeout).
            wait_for_ready: Wait (up to the deadline) for the connection instead of
                failing at once when the server is not reachable yet.

        Returns:
            True if the server reports SERVING; False if it is unreachable or not serving.
        """
        try:
            response = self._health.Check(
                health_pb2.HealthCheckRequest(service=""),
                timeout=self.timeout if timeout is None else timeout,
                wait_for_ready=wait_for_ready,
            )
        except grpc.RpcError:
            return False
        return response.status == health_pb2.HealthCheckResponse.SERVING

    def wait_ready(self, timeout: float = 10.0) -> None:
        """Blocks until the server is healthy.

        Raises:
            ServerUnavailable: If it is not healthy within ``timeout`` seconds.
        """
        self._wait_healthy(timeout, self.server)

    def create_session(
        self, config: SessionConfig | esa_pb2.SessionConfig, session_id: str | None = None
    ) -> Session:
        """Creates a session (or returns the existing one with this id and an identical config).

        Args:
            config: The config; a raw ``esa_pb2.SessionConfig`` is sent unchecked.
            session_id: 1 to 128 bytes; None lets the server generate a UUID.

        Raises:
            InvalidArgument: The server rejected the config or id.
            SessionAlreadyExists: The id exists with a different config.
            ResourceExhausted: The server's session limit is reached.
        """
        message = config.to_proto() if isinstance(config, SessionConfig) else config
        request = esa_pb2.CreateSessionRequest(session_id=session_id or "", config=message)
        response = call(self.stub.CreateSession, request, self.timeout)
        if not isinstance(config, SessionConfig):
            config = SessionConfig.from_proto(message)
        return Session(self, response.session_id, config)

    def session_state(self, session_id: str) -> SessionState:
        """Returns a snapshot of a session (``GetSession``)."""
        request = esa_pb2.GetSessionRequest(session_id=session_id)
        return SessionState.from_proto(call(self.stub.GetSession, request, self.timeout))

    def get_session(self, session_id: str) -> Session:
        """Returns a :class:`Session` bound to an existing server session, at its current step.

        Raises:
            SessionNotFound: If the id is unknown, closed or expired.
        """
        state = self.session_state(session_id)
        return Session(self, session_id, state.config, step=state.step)

    def create_batch(
        self,
        configs: SessionConfig | Sequence[SessionConfig],
        n: int | None = None,
        *,
        ids: Sequence[str] | None = None,
        use_stream: bool = False,
    ) -> SessionBatch:
        """Creates N sessions stepped together, e.g. one per env of a VecEnv.

        Args:
            configs: One config for all N sessions, or a sequence of N configs
                (all with the same ``action_dim``).
            n: Number of sessions (required with a single config).
            ids: Session ids; None = a random UUID per session (ids share nothing, so
                one id tells nothing about the others).
            use_stream: Carry probes and reports over one persistent ``StepStream``
                instead of ``ProbeBatch`` / ``ReportBatch`` calls.

        Returns:
            The batch. If creating one of the sessions fails, those already created
            are closed before the error is raised.
        """
        per_session = as_batch_configs(configs, n)
        if ids is None:
            ids = [str(uuid.uuid4()) for _ in per_session]
        if len(ids) != len(per_session):
            raise ValueError(f"expected {len(per_session)} ids, got {len(ids)}")
        created: list[Session] = []
        try:
            for session_id, config in zip(ids, per_session, strict=True):
                created.append(self.create_session(config, session_id))
        except BaseException:
            for session in created:
                with contextlib.suppress(EsaError):
                    session.close()
            raise
        return SessionBatch(self, [s.id for s in created], per_session, use_stream=use_stream)

    def restore_sessions(
        self, ids: Sequence[str], configs: SessionConfig | Sequence[SessionConfig]
    ) -> int:
        """Recreates, under the same ids and configs, those sessions the server no longer has.

        A session is lost when its server restarts or when it expires after ``--session-ttl``
        idle seconds; afterwards every call for it raises ``SessionNotFound``. ESA state is
        per episode, so a session recreated at the start of an episode behaves exactly like
        the lost one would have: what is lost is the shift of the episode that was running,
        the episode count (and with it the ``lr_decay`` and ``max_episodes`` progress) and
        the response normalization's running mean square. Call this when a call raised
        ``SessionNotFound``, then start a new episode (step 0, ``episode_start=True``).

        Args:
            ids: The session ids, e.g. ``batch.ids``.
            configs: One config for all, or one per id (e.g. ``batch.configs``).

        Returns:
            How many sessions were recreated (also added to :attr:`sessions_restored`).
        """
        per_session = as_batch_configs(configs, len(ids))
        restored = 0
        for session_id, config in zip(ids, per_session, strict=True):
            try:
                self.session_state(session_id)
            except SessionNotFound:
                self.create_session(config, session_id)
                restored += 1
        self.sessions_restored += restored
        return restored

    def batch_transport(
        self, ids: Sequence[str], action_dim: int, *, use_stream: bool = False
    ) -> BatchTransport:
        """What a :class:`SessionBatch` of these sessions sends its round trips through.

        Args:
            ids: The batch's session ids (transports that route by id need them).
            action_dim: The batch's shared action dimension.
            use_stream: Use the ``StepStream`` RPC instead of ``ProbeBatch`` / ``ReportBatch``.
        """
        transport = StreamTransport if use_stream else UnaryTransport
        return transport(self.stub, self.timeout)

    def close(self) -> None:
        """Closes the channel and stops the server if :meth:`spawn` started it. Idempotent."""
        if self._closed:
            return
        self._closed = True
        self._channel.close()
        if self.server is not None:
            self.server.stop()

    def __enter__(self) -> EsaClient:
        """Returns self."""
        return self

    def __exit__(self, *exc: object) -> None:
        """Closes the client."""
        self.close()

    def __copy__(self) -> EsaClient:
        """Returns self: a client is a handle on one connection (and server), shared not copied."""
        return self

    def __deepcopy__(self, memo: dict[int, object]) -> EsaClient:
        """Returns self (gymnasium deep-copies wrapper arguments to record them)."""
        return self

    def __repr__(self) -> str:
        """Shows the address and whether this client owns its server."""
        owned = f", server pid {self.server.pid}" if self.server is not None else ""
        return f"EsaClient({self.address!r}{owned})"
