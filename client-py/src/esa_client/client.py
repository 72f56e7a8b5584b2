"""``EsaClient``: the session API over a running server, a spawned one, or esa-core in-process."""

from __future__ import annotations

import contextlib
import os
import secrets
import time
import uuid
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Literal, TypeVar, Union, get_args

from ._proto.esa.v1 import esa_pb2
from .config import SessionConfig
from .errors import EsaError, ServerUnavailable, SessionNotFound, StatusCode, Unauthenticated
from .reconnect import DEFAULT_RECONNECT_TIMEOUT, Reconnect, check_reconnect_timeout
from .session import Session, SessionBatch, restore_sessions
from .sidecar import ServerProcess, limit_args
from .state import SessionProgress, SessionState, as_batch_configs
from .transports.base import Transport
from .transports.grpc import GrpcTransport, TlsConfig

if TYPE_CHECKING:
    import zenoh

TransportName = Literal["grpc", "zenoh"]
"""How :meth:`EsaClient.connect` and :meth:`EsaClient.spawn` reach the server."""

_TRANSPORTS: tuple[str, ...] = get_args(TransportName)

TOKEN_ENV = "ESA_AUTH_TOKEN"

Where = Union["EsaClient", str, None]
"""Where sessions live: a client, a string :meth:`EsaClient.open` parses, or None (in-process)."""

_Client = TypeVar("_Client", bound="EsaClient")


def check_timeout(timeout: float) -> float:
    """Returns ``timeout`` as a float if it is a positive number of seconds."""
    if not timeout > 0:
        raise ValueError(f"expected timeout > 0 seconds, got {timeout}")
    return float(timeout)


def resolve_token(token: str | None, token_file: str | os.PathLike[str] | None) -> str | None:
    """The auth token to send: ``token``, else ``token_file``'s content, else ``$ESA_AUTH_TOKEN``.

    Stripped of surrounding whitespace, as the server strips its ``--auth-token-file``.

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


def _check_transport(transport: str, **zenoh_only: object) -> None:
    """Raises ValueError for an unknown transport, or Zenoh options given to gRPC."""
    if transport not in _TRANSPORTS:
        raise ValueError(f"expected transport in {_TRANSPORTS}, got {transport!r}")
    given = sorted(name for name, value in zenoh_only.items() if value is not None)
    if transport != "zenoh" and given:
        raise ValueError(f"expected {', '.join(given)} with transport='zenoh' only")


def _grpc_transport(
    address: str, timeout: float, token: str | None, tls: TlsConfig | None
) -> GrpcTransport:
    """The gRPC transport to ``address``, checked."""
    if address.startswith("unix:"):
        if len(address) <= len("unix:"):
            raise ValueError(f"expected 'unix:/path/to/socket', got {address!r}")
        if tls is not None:
            raise ValueError(
                f"expected a host:port address with tls (the server serves TLS on TCP only), "
                f"got {address!r}"
            )
    else:
        host, sep, port = address.rpartition(":")
        if not sep or not host or not port.isdigit():
            raise ValueError(f"expected 'host:port' or 'unix:/path', got {address!r}")
    return GrpcTransport(address, timeout, token, tls)


def _spawn_zenoh(
    binary: str | os.PathLike[str] | None,
    args: Sequence[str],
    shards: int | None,
    prefix: str | None,
    servers: list[ServerProcess],
    timeout: float,
    startup_timeout: float,
) -> tuple[Transport, str]:
    """Starts ``esa-server --zenoh`` (``--shard i/N``) into ``servers``: transport, address.

    A loopback port is open to every local user, so the servers require a fresh random token.
    """
    from .transports.zenoh import DEFAULT_PREFIX, ZenohTransport, check_prefix, check_shards

    check_shards(shards)
    zenoh_prefix = check_prefix(DEFAULT_PREFIX if prefix is None else prefix)
    token = secrets.token_urlsafe(32)
    locators: list[str] = []
    for i in range(shards or 1):
        shard = [] if shards is None else ["--shard", f"{i}/{shards}"]
        extra = ["--zenoh", *shard, "--zenoh-prefix", zenoh_prefix, *args]
        server = ServerProcess(binary, token=token, extra_args=extra)
        servers.append(server)
        announced = server.announced("zenoh listening on ", startup_timeout)
        if not announced:
            raise ServerUnavailable(
                f"{server.binary} announced no Zenoh locator; its output:\n{server.output_tail()}",
                StatusCode.UNAVAILABLE,
            )
        locators += announced
    transport = ZenohTransport.open(
        locators, prefix=zenoh_prefix, timeout=timeout, token=token, shards=shards, config=None
    )
    return transport, ",".join(locators)


class EsaClient:
    """A client of esa sessions, built by :meth:`connect`, :meth:`spawn` or :meth:`in_process`.

    Every call has a deadline of ``timeout`` seconds; only a batch rides out a lost connection
    (the client guide's "Errors, deadlines and restarts").

    Example::

        with EsaClient.spawn() as client:
            session = client.create_session(SessionConfig(1, 0.05, 0.2, 10.0, 0.1))
            probe = session.probe([0.3], episode_start=True)
            action = session.report(q_value=critic(obs, probe))

    Args:
        transport: A :class:`~esa_client.transports.base.Transport`; the client closes it.
        address: Where the transport goes, for messages.
        timeout: The per-call deadline of the transport, in seconds.

    Attributes:
        servers: The server processes :meth:`spawn` started (``servers[i]`` serves shard
            i), stopped by :meth:`close`; empty otherwise.
        sessions_restored: How many sessions :meth:`restore_sessions` (or a batch) recreated.
        reconnect_timeout: Seconds a batch retries a lost server before it raises; 0 = at once
            (default 60).
    """

    def __init__(self, transport: Transport, *, address: str, timeout: float) -> None:
        """Takes ownership of ``transport``.

        Raises:
            TypeError: If ``transport`` is an address (use :meth:`connect`).
        """
        if isinstance(transport, str):
            raise TypeError(
                f"expected a Transport, got the address {transport!r}: "
                f"use EsaClient.connect({transport!r})"
            )
        self.transport = transport
        self.address = address
        self.timeout = timeout
        self.servers: tuple[ServerProcess, ...] = ()
        self.sessions_restored = 0
        self.reconnect_timeout = DEFAULT_RECONNECT_TIMEOUT
        self._closed = False

    @classmethod
    def connect(
        cls,
        address: str | Sequence[str],
        *,
        transport: TransportName = "grpc",
        timeout: float = 5.0,
        token: str | None = None,
        token_file: str | os.PathLike[str] | None = None,
        tls: TlsConfig | None = None,
        shards: int | None = None,
        prefix: str | None = None,
        zenoh_config: zenoh.Config | None = None,
        check: bool = True,
        reconnect_timeout: float = DEFAULT_RECONNECT_TIMEOUT,
    ) -> EsaClient:
        """A client of the running server(s) at ``address``, over ``transport``.

        Args:
            address: gRPC: ``host:port`` or ``unix:/path/to/socket``. Zenoh: the
                endpoint(s) of the server or router, e.g. ``tcp/127.0.0.1:7447``.
            transport: ``"grpc"`` or ``"zenoh"`` (extra ``esa-client[zenoh]``), the same API.
            timeout: Deadline in seconds for every call (and, over Zenoh, connecting).
            token: The servers' auth token (``--auth-token-file``), sent with every call.
            token_file: A file holding the token instead; with neither, ``$ESA_AUTH_TOKEN``.
            tls: gRPC over TLS (``"grpc"`` only), see :class:`~esa_client.TlsConfig`.
            shards: Zenoh only: N servers started with ``--shard i/N``.
            prefix: Zenoh only: the servers' ``--zenoh-prefix`` (default ``esa/v1``).
            zenoh_config: Zenoh only: a complete Zenoh config instead of the peer config
                built from ``address`` (e.g. client mode to a ``zenohd`` router).
            check: Before returning, :meth:`check` the servers within ``timeout``, so that a
                wrong address or token fails here; False sends nothing until the first call.
            reconnect_timeout: The client's :attr:`reconnect_timeout`.

        Raises:
            ValueError: A malformed argument, or one the transport does not take.
            OSError: If a token or TLS file cannot be read.
            ServerUnavailable: ``check`` and no server answered in time.
            Unauthenticated: ``check`` and a server refused the token.
        """
        _check_transport(transport, shards=shards, prefix=prefix, zenoh_config=zenoh_config)
        reconnect_timeout = check_reconnect_timeout(reconnect_timeout)
        timeout = check_timeout(timeout)
        resolved = resolve_token(token, token_file)
        opened: Transport
        if transport == "zenoh":
            if tls is not None:
                raise ValueError("expected tls=None with transport='zenoh' (use zenoh_config)")
            from .transports.zenoh import DEFAULT_PREFIX, ZenohTransport

            opened = ZenohTransport.open(
                address,
                prefix=DEFAULT_PREFIX if prefix is None else prefix,
                timeout=timeout,
                token=resolved,
                shards=shards,
                config=zenoh_config,
            )
        elif isinstance(address, str):
            opened = _grpc_transport(address, timeout, resolved, tls)
        else:
            raise ValueError(f"expected one 'host:port' or 'unix:/path' address, got {address!r}")
        where = address if isinstance(address, str) else ",".join(address)
        client = cls(opened, address=where, timeout=timeout)
        client.reconnect_timeout = reconnect_timeout
        if check:
            try:
                client.check(timeout)
            except BaseException:
                client.close()
                raise
        return client

    @classmethod
    def open(cls, where: str) -> EsaClient:
        """A client of the sessions that ``where`` names, with every option at its default.

        The one parser of the strings that the drop-ins' ``esa_client`` takes.

        Args:
            where: ``"in-process"`` (esa-core in this process), ``"spawn"`` (a private
                server), ``"zenoh:<endpoint>"``, or a gRPC ``host:port`` or ``unix:/path``.

        Raises:
            ValueError: If ``where`` is none of these.
            ServerUnavailable: If no server answers at the address (:meth:`check`).
            Unauthenticated: If the server requires a token (give it with :meth:`connect`).
        """
        if not isinstance(where, str):
            raise ValueError(f"expected a string naming where the sessions live, got {where!r}")
        if where == "in-process":
            return cls.in_process()
        if where == "spawn":
            return cls.spawn()
        if where.startswith("zenoh:"):
            return cls.connect(where.removeprefix("zenoh:"), transport="zenoh")
        if where.startswith("unix:") or ":" in where:
            return cls.connect(where)
        raise ValueError(
            "expected 'in-process', 'spawn', 'zenoh:<endpoint>', 'host:port' or "
            f"'unix:/path', got {where!r}"
        )

    def check(self, timeout: float | None = None) -> None:
        """Checks that every server behind this client answers and takes its token.

        Health checks need no token, so this also looks up a session id no trainer uses.

        Args:
            timeout: Seconds to wait for the servers (default: the client's timeout).

        Raises:
            ServerUnavailable: No server answered in time.
            Unauthenticated: A server refused this client's token.
        """
        bound = self.timeout if timeout is None else check_timeout(timeout)
        if not self.healthy(timeout=bound, wait_for_ready=True):
            raise ServerUnavailable(
                f"no esa server answered at {self.address} within {bound:g} s: start one "
                "there (esa-server --listen HOST:PORT), correct the address (or, over TLS, "
                "the CA and server name), or keep the sessions in this process "
                "(EsaClient.in_process(), or esa_client=None for a drop-in)",
                StatusCode.UNAVAILABLE,
            )
        try:
            self.transport.get_session("esa-client-access-check")
        except SessionNotFound:
            return
        except Unauthenticated as err:
            raise Unauthenticated(
                f"esa server at {self.address} refused this client ({err.message}): pass "
                f"its token as token= or token_file=, or set ${TOKEN_ENV}",
                err.code,
            ) from err

    @classmethod
    def spawn(
        cls,
        binary: str | os.PathLike[str] | None = None,
        *,
        transport: TransportName = "grpc",
        shards: int | None = None,
        session_ttl: float | None = None,
        max_sessions: int | None = None,
        max_session_memory: int | None = None,
        extra_args: Sequence[str] = (),
        timeout: float = 5.0,
        startup_timeout: float = 30.0,
        prefix: str | None = None,
        reconnect_timeout: float = DEFAULT_RECONNECT_TIMEOUT,
    ) -> EsaClient:
        """Starts a private esa-server and returns a client connected to it.

        gRPC: a private Unix socket; Zenoh: loopback (``shards=N``: N processes) and a fresh
        random token (``client.servers[i].token``). They stop with :meth:`close` or the process.

        Args:
            binary: Path of the esa-server executable; None searches for it.
            transport: ``"grpc"`` or ``"zenoh"``, as in :meth:`connect`.
            shards: Zenoh only: N server processes, sessions routed between them.
            session_ttl: Idle-session expiry in seconds, 0 = never; None = server default (600).
            max_sessions: Live-session limit (per shard); None = the server's default (100,000).
            max_session_memory: Session memory budget in bytes (per shard); None = the
                server's default (half of the memory it may use).
            extra_args: Further arguments for every server.
            timeout: Per-call deadline of the returned client.
            startup_timeout: Seconds to wait for each server to report healthy.
            prefix: Zenoh only: the ``--zenoh-prefix`` to serve and use.
            reconnect_timeout: The client's :attr:`reconnect_timeout`.

        Raises:
            ValueError: If a limit is not a number at least its minimum, or an argument
                does not go with the transport.
            EsaError: If the binary cannot be found or built.
            ServerUnavailable: If a server exits or is not healthy in time (with its output).
        """
        _check_transport(transport, shards=shards, prefix=prefix)
        reconnect_timeout = check_reconnect_timeout(reconnect_timeout)
        timeout = check_timeout(timeout)
        args = [*limit_args(session_ttl, max_sessions, max_session_memory), *extra_args]
        servers: list[ServerProcess] = []
        client: EsaClient | None = None
        # Whatever fails, no server started here outlives the error.
        try:
            if transport == "zenoh":
                opened, address = _spawn_zenoh(
                    binary, args, shards, prefix, servers, timeout, startup_timeout
                )
            else:
                servers.append(ServerProcess(binary, extra_args=args))
                address = servers[0].address
                opened = _grpc_transport(address, timeout, None, None)
            client = cls(opened, address=address, timeout=timeout)
            client.servers = tuple(servers)
            client._wait_healthy(startup_timeout)
        except BaseException:
            if client is not None:
                client.close()
            for server in servers:
                server.stop()
            raise
        client.reconnect_timeout = reconnect_timeout
        return client

    @classmethod
    def in_process(cls, *, max_sessions: int | None = None) -> EsaClient:
        """A client of esa-core in this process: the same API and bits, no server and no socket.

        Args:
            max_sessions: Live-session limit; None = the server's default (100,000).
        """
        # Imported here: the extension module loads only for those who use it.
        from .transports.in_process import InProcessTransport

        transport = InProcessTransport(max_sessions=max_sessions)
        return cls(transport, address="in-process", timeout=float("inf"))

    @property
    def server(self) -> ServerProcess | None:
        """The one server :meth:`spawn` started (None if it started N shards, or none)."""
        return self.servers[0] if len(self.servers) == 1 else None

    def _wait_healthy(self, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while True:
            for server in self.servers:
                server.check_running()
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                tails = "".join(
                    f"; {server.binary} (pid {server.pid}) output:\n{server.output_tail()}"
                    for server in self.servers
                )
                raise ServerUnavailable(
                    f"esa server at {self.address} not healthy within {timeout} s{tails}",
                    StatusCode.UNAVAILABLE,
                )
            # Short waits so that a crashed server process is noticed promptly.
            if self.healthy(timeout=min(0.25, remaining), wait_for_ready=True):
                return

    def healthy(self, *, timeout: float | None = None, wait_for_ready: bool = False) -> bool:
        """True if every server behind this client is serving.

        Args:
            timeout: Deadline in seconds (default: the client's timeout).
            wait_for_ready: Wait (up to the deadline) for a server not reachable yet.
        """
        bound = self.timeout if timeout is None else timeout
        return self.transport.healthy(bound, wait_for_ready=wait_for_ready)

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

        If creating a session fails, those created are closed first.

        Args:
            configs: One config for all N sessions, or N configs (one ``action_dim``).
            n: Number of sessions (required with a single config).
            ids: Session ids; None = a random UUID per session.
            use_stream: Carry probes and reports over one persistent gRPC ``StepStream``
                (in-process and Zenoh batches have no stream to keep).
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
            reconnect=Reconnect(self.address, self.reconnect_timeout, closed=lambda: self._closed),
        )

    def restore_sessions(
        self,
        ids: Sequence[str],
        configs: SessionConfig | Sequence[SessionConfig],
        progress: Sequence[SessionProgress | None] | None = None,
    ) -> int:
        """Recreates, under the same ids and configs, those sessions the server no longer has.

        Call it when calls raise ``SessionNotFound``, then start a new episode; a batch does it
        itself (:meth:`SessionBatch.restore`; the client guide's "Errors, deadlines and restarts").

        Args:
            ids: The session ids, e.g. ``batch.ids``.
            configs: One config for all, or one per id (e.g. ``batch.configs``).
            progress: The progress each recreated session resumes (e.g. a snapshot's), one
                per id; None (for an item or all): a new session's.

        Returns:
            How many sessions were recreated (also added to :attr:`sessions_restored`).

        Raises:
            ValueError: ``progress`` does not have one item per id.
        """
        restored = restore_sessions(self.transport, ids, configs, progress)
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
        for server in self.servers:
            server.stop()

    def __enter__(self: _Client) -> _Client:
        """Returns self."""
        return self

    def __exit__(self, *exc: object) -> None:
        """Closes the client."""
        self.close()

    def __copy__(self: _Client) -> _Client:
        """Returns self: a client is a handle on one connection, shared not copied."""
        return self

    def __deepcopy__(self: _Client, memo: dict[int, object]) -> _Client:
        """Returns self (gymnasium deep-copies wrapper arguments to record them)."""
        return self

    def __repr__(self) -> str:
        """Shows the address, the transport and the servers this client owns."""
        owned = "".join(f", server pid {server.pid}" for server in self.servers)
        return f"EsaClient({self.address!r}, {self.transport!r}{owned})"


def resolve_client(where: Where) -> tuple[EsaClient, bool]:
    """The client that ``where`` names, and whether the caller opened it (and so closes it).

    Args:
        where: An :class:`EsaClient` (used as it is; it stays the caller's), a string
            :meth:`EsaClient.open` parses, or None for ``EsaClient.in_process()``.

    Raises:
        ValueError: If ``where`` is none of these.
        ServerUnavailable: If no server answers at a given address.
        Unauthenticated: If the server there refuses the client.
    """
    if isinstance(where, EsaClient):
        return where, False
    if where is None:
        return EsaClient.in_process(), True
    if isinstance(where, str):
        return EsaClient.open(where), True
    raise ValueError(
        f"expected an EsaClient, a string such as '127.0.0.1:50051' or 'spawn', or None "
        f"(in-process), got {where!r}"
    )
