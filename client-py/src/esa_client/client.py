"""The clients: a transport chosen and owned, and the session API on top of it.

:class:`BaseClient` is the API every client shares (sessions, batches, restoring lost
sessions, health), written against :class:`~esa_client.transport.Transport`.
:class:`EsaClient` is the gRPC factory: it opens a
:class:`~esa_client.grpc_transport.GrpcTransport`, optionally to a server it starts
itself, and closes both. The Zenoh and sharded factories are in
:mod:`esa_client.zenoh_client`.
"""

from __future__ import annotations

import contextlib
import os
import time
import uuid
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

import grpc

from ._proto.esa.v1 import esa_pb2
from .config import SessionConfig
from .errors import EsaError, ServerUnavailable
from .grpc_transport import GrpcTransport, TlsConfig
from .session import Session, SessionBatch, restore_sessions
from .sidecar import ServerProcess
from .state import SessionState, as_batch_configs
from .stub_transport import ServiceStub
from .transport import Transport

if TYPE_CHECKING:
    from .native_transport import NativeGrpcTransport


def _check_address(address: str) -> str:
    if address.startswith("unix:"):
        if len(address) <= len("unix:"):
            raise ValueError(f"expected 'unix:/path/to/socket', got {address!r}")
        return address
    host, sep, port = address.rpartition(":")
    if not sep or not host or not port.isdigit():
        raise ValueError(f"expected 'host:port' or 'unix:/path', got {address!r}")
    return address


def check_timeout(timeout: float) -> float:
    """Returns ``timeout`` as a float if it is a positive number of seconds."""
    if not timeout > 0:
        raise ValueError(f"expected timeout > 0 seconds, got {timeout}")
    return float(timeout)


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


_Client = TypeVar("_Client", bound="BaseClient")


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
        client.on_close(server.stop)
        client._wait_healthy(startup_timeout, server)
    except BaseException:
        server.stop()
        raise
    return client


class BaseClient:
    """The session API over a :class:`~esa_client.transport.Transport` the client owns.

    ``EsaClient``, ``ZenohEsaClient`` and ``ShardedEsaClient`` are this API over gRPC,
    Zenoh and N shards. A client closes its transport, then whatever it registered with
    :meth:`on_close` (a Zenoh session, the servers it spawned), in that order.

    Args:
        transport: The transport; the client closes it.
        address: Where the transport goes, for messages.
        timeout: The per-call deadline of the transport, in seconds.

    Attributes:
        transport: The transport.
        address: Where it goes.
        timeout: The per-call deadline in seconds.
        server: The :class:`~esa_client.sidecar.ServerProcess` when started by ``spawn``,
            else None.
        sessions_restored: How many sessions :meth:`restore_sessions` (or a batch's
            :meth:`~esa_client.SessionBatch.restore`) recreated.
    """

    def __init__(self, transport: Transport, *, address: str, timeout: float) -> None:
        """Takes ownership of ``transport``."""
        self.transport = transport
        self.address = address
        self.timeout = timeout
        self.server: ServerProcess | None = None
        self.sessions_restored = 0
        self._closers: list[Callable[[], None]] = []
        self._closed = False

    def on_close(self, release: Callable[[], None]) -> None:
        """Runs ``release()`` when the client closes, after its transport (in call order)."""
        self._closers.append(release)

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
        """True if every server behind this client is serving.

        Args:
            timeout: Deadline in seconds (default: the client's timeout).
            wait_for_ready: Wait (up to the deadline) for the connection instead of
                failing at once when the server is not reachable yet.

        Returns:
            True if the servers answer as serving; False if one is unreachable or not serving.
        """
        bound = self.timeout if timeout is None else timeout
        return self.transport.healthy(bound, wait_for_ready=wait_for_ready)

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
        created = self.transport.create_session(session_id or "", message)
        if not isinstance(config, SessionConfig):
            config = SessionConfig.from_proto(message)
        return Session(self.transport, created, config)

    def session_state(self, session_id: str) -> SessionState:
        """Returns a snapshot of a session (``GetSession``)."""
        return self.transport.get_session(session_id)

    def get_session(self, session_id: str) -> Session:
        """Returns a :class:`Session` bound to an existing server session, at its current step.

        Raises:
            SessionNotFound: If the id is unknown, closed or expired.
        """
        state = self.session_state(session_id)
        return Session(self.transport, session_id, state.config, step=state.step)

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
        created: list[str] = []
        try:
            for session_id, config in zip(ids, per_session, strict=True):
                created.append(self.transport.create_session(session_id, config.to_proto()))
        except BaseException:
            for session_id in created:
                with contextlib.suppress(EsaError):
                    self.transport.close_session(session_id)
            raise
        return SessionBatch(
            self.transport,
            created,
            per_session,
            use_stream=use_stream,
            on_restore=self._count_restored,
        )

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
        restored = restore_sessions(self.transport, ids, configs)
        self._count_restored(restored)
        return restored

    def _count_restored(self, sessions: int) -> None:
        self.sessions_restored += sessions

    def close(self) -> None:
        """Closes the transport, then stops the servers :meth:`spawn` started. Idempotent."""
        if self._closed:
            return
        self._closed = True
        self.transport.close()
        for release in self._closers:
            release()

    def __enter__(self: _Client) -> _Client:
        """Returns self."""
        return self

    def __exit__(self, *exc: object) -> None:
        """Closes the client."""
        self.close()

    def __copy__(self: _Client) -> _Client:
        """Returns self: a client is a handle on one connection (and server), shared not copied."""
        return self

    def __deepcopy__(self: _Client, memo: dict[int, object]) -> _Client:
        """Returns self (gymnasium deep-copies wrapper arguments to record them)."""
        return self

    def __repr__(self) -> str:
        """Shows the address and whether this client owns its server."""
        owned = f", server pid {self.server.pid}" if self.server is not None else ""
        return f"{type(self).__name__}({self.address!r}{owned})"


class EsaClient(BaseClient):
    """A connection to an esa server over gRPC.

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
        tls: Connect over TLS (a server started with ``--tls-cert``), e.g.
            ``TlsConfig(ca="ca.pem")``, with ``cert=`` and ``key=`` for mutual TLS; the
            token then travels encrypted. None: plaintext (loopback or a Unix socket).
        native: Call through the Rust gRPC client of ``esa_client._native``
            (:class:`~esa_client.native_transport.NativeGrpcTransport`: several times
            faster per round trip, no TLS, no ``StepStream``) instead of grpcio.

    Attributes:
        address: The gRPC target.
        timeout: The per-call deadline in seconds.
        stub: The generated ``EsaServiceStub`` (for raw access to the wire API); grpcio's
            only, so not with ``native=True``.
        transport: The :class:`~esa_client.grpc_transport.GrpcTransport`, or the
            :class:`~esa_client.native_transport.NativeGrpcTransport` with ``native=True``.
        server: The :class:`~esa_client.sidecar.ServerProcess` when started by
            :meth:`spawn`, else None.
        sessions_restored: How many sessions :meth:`restore_sessions` recreated.
    """

    transport: GrpcTransport | NativeGrpcTransport

    def __init__(
        self,
        address: str = "127.0.0.1:50051",
        *,
        timeout: float = 5.0,
        token: str | None = None,
        token_file: str | os.PathLike[str] | None = None,
        tls: TlsConfig | None = None,
        native: bool = False,
    ) -> None:
        """Opens a channel to ``address`` (connecting lazily).

        Raises:
            ValueError: If the address, timeout or token is malformed, or TLS is asked for
                on a Unix socket (the server serves TLS on TCP only) or with ``native``.
            OSError: If a token or TLS file cannot be read.
        """
        timeout = check_timeout(timeout)
        address = _check_address(address)
        if tls is not None and address.startswith("unix:"):
            raise ValueError(
                f"expected a host:port address with tls (the server serves TLS on TCP only), "
                f"got {address!r}"
            )
        resolved = resolve_token(token, token_file)
        transport: GrpcTransport | NativeGrpcTransport
        if native:
            if tls is not None:
                raise ValueError("expected tls=None with native=True (grpcio serves TLS)")
            # Imported here: the extension module loads only for those who use it.
            from .native_transport import NativeGrpcTransport

            transport = NativeGrpcTransport(address, timeout, resolved)
        else:
            transport = GrpcTransport(address, timeout, resolved, tls)
            self._channel = transport.channel
        super().__init__(transport, address=address, timeout=timeout)

    @property
    def stub(self) -> ServiceStub:
        """The generated ``EsaServiceStub`` of the grpcio channel.

        Raises:
            AttributeError: With ``native=True`` (no grpcio channel).
        """
        if not isinstance(self.transport, GrpcTransport):
            raise AttributeError("EsaClient(native=True) has no grpcio stub")
        return self.transport.stub

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
        native: bool = False,
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
            native: Call through the Rust gRPC client instead of grpcio (see :class:`EsaClient`).

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
            server, lambda: cls(server.address, timeout=timeout, native=native), startup_timeout
        )

    @staticmethod
    def in_process(*, max_sessions: int | None = None) -> BaseClient:
        """A client of the in-process engine: the same API, no server and no socket.

        The engine (``esa_client._native``) is esa-core compiled into this package: the
        server's update law, checks and typed errors, bit for bit, at a few microseconds
        per batch round trip. Its sessions live in this process only; use :meth:`spawn`
        or a server address to share them across processes, machines or languages.

        Args:
            max_sessions: Live-session limit; None = the server's default (100,000).

        Returns:
            A client over :class:`~esa_client.inprocess_transport.InProcessTransport`.
        """
        # Imported here: the extension module loads only for those who use it.
        from .inprocess_transport import InProcessTransport

        transport = InProcessTransport(max_sessions=max_sessions)
        return BaseClient(transport, address="in-process", timeout=float("inf"))
