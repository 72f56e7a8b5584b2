"""``EsaClient``: the one way to build a client, whatever the transport.

- :meth:`EsaClient.connect` reaches a running server: over gRPC (grpcio, the default),
  over gRPC through the Rust client of ``esa_client._native`` (``transport="native"``),
  or over Zenoh (``transport="zenoh"``, one server or ``shards=N``);
- :meth:`EsaClient.spawn` starts a private server first (gRPC on a Unix socket, or
  ``esa-server --zenoh`` on loopback, N of them with ``shards=N``) and owns it;
- :meth:`EsaClient.in_process` needs no server: esa-core compiled into this package.

Every one returns a :class:`~esa_client.base_client.BaseClient`: the same session API
over its :class:`~esa_client.transports.base.Transport` (:mod:`esa_client.transports`).
The older constructors, ``EsaClient(address, native=...)``, ``ZenohEsaClient(...)`` and
``ShardedEsaClient(...)``, still work for this release and are deprecated.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from functools import partial
from typing import TYPE_CHECKING, Literal, get_args

from .base_client import BaseClient, check_timeout, connect_spawned, resolve_token
from .reconnect import DEFAULT_RECONNECT_TIMEOUT, check_reconnect_timeout
from .sidecar import ServerProcess
from .transports.grpcio import GrpcTransport, TlsConfig
from .transports.stub import ServiceStub

if TYPE_CHECKING:
    import zenoh

    from .transports.native import NativeGrpcTransport

TransportName = Literal["grpc", "native", "zenoh"]
"""How :meth:`EsaClient.connect` and :meth:`EsaClient.spawn` reach the server."""

_TRANSPORTS: tuple[str, ...] = get_args(TransportName)


def _check_address(address: str) -> str:
    if address.startswith("unix:"):
        if len(address) <= len("unix:"):
            raise ValueError(f"expected 'unix:/path/to/socket', got {address!r}")
        return address
    host, sep, port = address.rpartition(":")
    if not sep or not host or not port.isdigit():
        raise ValueError(f"expected 'host:port' or 'unix:/path', got {address!r}")
    return address


def _check_transport(transport: str, **zenoh_only: object) -> None:
    """Raises ValueError for an unknown transport, or Zenoh options given to gRPC."""
    if transport not in _TRANSPORTS:
        raise ValueError(f"expected transport in {_TRANSPORTS}, got {transport!r}")
    given = sorted(name for name, value in zenoh_only.items() if value is not None)
    if transport != "zenoh" and given:
        raise ValueError(f"expected {', '.join(given)} with transport='zenoh' only")


class EsaClient(BaseClient):
    """A client of an esa server: build one with :meth:`connect`, :meth:`spawn`, :meth:`in_process`.

    Every call has a deadline of ``timeout`` seconds; a lost connection raises
    :class:`~esa_client.errors.ServerUnavailable` at once instead of waiting, except in a
    batch (:meth:`create_batch`), which retries for up to ``reconnect_timeout`` seconds
    (set by :meth:`connect` and :meth:`spawn`, default 60) and then raises it.

    Example::

        with EsaClient.spawn() as client:
            session = client.create_session(SessionConfig(1, 0.05, 0.2, 10.0, 0.1))
            probe = session.probe([0.3], episode_start=True)
            action = session.report(q_value=critic(obs, probe))

    An ``EsaClient`` instance is the gRPC client (grpcio, or the Rust client); the
    constructor itself is what :meth:`connect` calls for those two transports.

    .. deprecated::
        Calling ``EsaClient(address, ...)`` directly, and its ``native=True``, are kept
        for one release: use ``EsaClient.connect(address)`` and
        ``EsaClient.connect(address, transport="native")``.

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
            (:class:`~esa_client.transports.native.NativeGrpcTransport`: several times
            faster per round trip, ``StepStream`` batches, no TLS) instead of grpcio.

    Attributes:
        address: The gRPC target.
        timeout: The per-call deadline in seconds.
        stub: The generated ``EsaServiceStub`` (for raw access to the wire API); grpcio's
            only, so not with ``native=True``.
        transport: The :class:`~esa_client.transports.grpcio.GrpcTransport`, or the
            :class:`~esa_client.transports.native.NativeGrpcTransport` with ``native=True``.
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
            from .transports.native import NativeGrpcTransport

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
        wait_ready: bool | None = None,
        reconnect_timeout: float = DEFAULT_RECONNECT_TIMEOUT,
    ) -> BaseClient:
        """A client of the running server(s) at ``address``, over ``transport``.

        Example::

            EsaClient.connect("127.0.0.1:50051")                     # grpcio
            EsaClient.connect("unix:/run/esa.sock", transport="native")
            EsaClient.connect("tcp/10.0.0.5:7447", transport="zenoh", shards=4)

        Args:
            address: gRPC (``"grpc"``, ``"native"``): ``host:port`` or
                ``unix:/path/to/socket``. Zenoh: the endpoint(s) of the server or router,
                e.g. ``tcp/127.0.0.1:7447``.
            transport: ``"grpc"`` (grpcio: TLS, ``StepStream``), ``"native"`` (the Rust
                gRPC client: faster per round trip, ``StepStream``, no TLS) or
                ``"zenoh"`` (extra ``esa-client[zenoh]``).
            timeout: Deadline in seconds for every call (and, over Zenoh, connecting).
            token: The servers' auth token (``--auth-token-file``).
            token_file: A file holding the token instead; with neither,
                ``$ESA_AUTH_TOKEN`` if set.
            tls: gRPC over TLS (``"grpc"`` only), see :class:`~esa_client.TlsConfig`.
            shards: Zenoh only: N servers started with ``--shard i/N``; sessions are
                routed by :func:`esa_client.sharding.shard_of`.
            prefix: Zenoh only: the servers' ``--zenoh-prefix`` (default ``esa/v1``).
            zenoh_config: Zenoh only: a complete Zenoh config instead of the peer config
                built from ``address`` (e.g. client mode to a ``zenohd`` router).
            wait_ready: Wait (up to ``timeout``) until every server answers before
                returning. None: Zenoh waits, gRPC connects lazily on the first call.
            reconnect_timeout: How long the client's batches retry (capped exponential
                backoff with jitter) when the server is unreachable, restarting or
                stalled, before they raise ``ServerUnavailable``; 0: raise at once.

        Returns:
            An :class:`EsaClient` for gRPC; for Zenoh a ``ZenohEsaClient`` (one server)
            or a ``ShardedEsaClient`` (``shards=N``), with the same API.

        Raises:
            ValueError: A malformed argument, or one the transport does not take.
            ServerUnavailable: ``wait_ready`` and no server answered in time.
        """
        _check_transport(transport, shards=shards, prefix=prefix, zenoh_config=zenoh_config)
        reconnect_timeout = check_reconnect_timeout(reconnect_timeout)
        if transport == "zenoh":
            if tls is not None:
                raise ValueError("expected tls=None with transport='zenoh' (use zenoh_config)")
            from .transports.zenoh_query import DEFAULT_PREFIX
            from .zenoh_client import ShardedEsaClient, ZenohEsaClient

            zenoh_client = (
                ZenohEsaClient if shards is None else partial(ShardedEsaClient, shards=shards)
            )
            zenoh_made: BaseClient = zenoh_client(
                address,
                prefix=DEFAULT_PREFIX if prefix is None else prefix,
                timeout=timeout,
                config=zenoh_config,
                wait_ready=wait_ready is not False,
                token=token,
                token_file=token_file,
            )
            zenoh_made.reconnect_timeout = reconnect_timeout
            return zenoh_made
        if not isinstance(address, str):
            raise ValueError(f"expected one 'host:port' or 'unix:/path' address, got {address!r}")
        client: BaseClient = cls(
            address,
            timeout=timeout,
            token=token,
            token_file=token_file,
            tls=tls,
            native=transport == "native",
        )
        client.reconnect_timeout = reconnect_timeout
        if wait_ready:
            try:
                client.wait_ready(client.timeout)
            except BaseException:
                client.close()
                raise
        return client

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
        native: bool = False,
        reconnect_timeout: float = DEFAULT_RECONNECT_TIMEOUT,
    ) -> BaseClient:
        """Starts a private esa-server and returns a client connected to it.

        gRPC (``"grpc"``, ``"native"``): the server listens on a Unix socket in a private
        directory. Zenoh: ``esa-server --zenoh`` on loopback, N processes (``--shard
        i/N``) with ``shards=N``; each also serves gRPC on a private socket
        (``client.server.address``, ``client.servers[i].address``) and requires a fresh
        random token (``client.server.token``), since a loopback port is open to every
        local user.

        The server is found via ``binary``, ``ESA_SERVER_BIN``, ``PATH`` or a cargo
        build of this repository (see :func:`esa_client.sidecar.find_server_binary`),
        and stopped by :meth:`close` (or at interpreter exit at the latest); if this
        process dies first, whatever the signal, the server stops by itself.

        Args:
            binary: Path of the esa-server executable; None searches for it.
            transport: ``"grpc"``, ``"native"`` or ``"zenoh"``, as in :meth:`connect`.
            shards: Zenoh only: N server processes, sessions routed between them.
            session_ttl: Idle-session expiry in seconds (0 = never); None = the server's
                default (600).
            max_sessions: Live-session limit (per shard); None = the server's default
                (100,000).
            max_session_memory: Session memory budget in bytes (per shard); None = the
                server's default (half of the memory it may use).
            extra_args: Further server arguments.
            timeout: Per-call deadline of the returned client.
            startup_timeout: Seconds to wait for the server to report healthy.
            prefix: Zenoh only: the ``--zenoh-prefix`` to serve and use.
            native: Deprecated (kept for one release): ``transport="native"``.
            reconnect_timeout: As for :meth:`connect`.

        Returns:
            An :class:`EsaClient` for gRPC; for Zenoh a ``ZenohEsaClient`` or, with
            ``shards``, a ``ShardedEsaClient``.

        Raises:
            ValueError: If a limit is not a number at least its minimum, or an argument
                does not go with the transport.
            EsaError: If the binary cannot be found or built.
            ServerUnavailable: If the server exits or is not healthy in time (with its output).
        """
        if native:
            transport = "native"
        _check_transport(transport, shards=shards, prefix=prefix)
        reconnect_timeout = check_reconnect_timeout(reconnect_timeout)
        client = cls._spawn(
            binary,
            transport,
            shards,
            session_ttl,
            max_sessions,
            max_session_memory,
            extra_args,
            timeout,
            startup_timeout,
            prefix,
        )
        client.reconnect_timeout = reconnect_timeout
        return client

    @classmethod
    def _spawn(
        cls,
        binary: str | os.PathLike[str] | None,
        transport: TransportName,
        shards: int | None,
        session_ttl: float | None,
        max_sessions: int | None,
        max_session_memory: int | None,
        extra_args: Sequence[str],
        timeout: float,
        startup_timeout: float,
        prefix: str | None,
    ) -> BaseClient:
        """What :meth:`spawn` starts and connects, before its reconnect deadline is set."""
        if transport == "zenoh":
            from .transports.zenoh_query import DEFAULT_PREFIX
            from .zenoh_client import ShardedEsaClient, ZenohEsaClient

            spawn_zenoh = (
                ZenohEsaClient.spawn
                if shards is None
                else partial(ShardedEsaClient.spawn, shards=shards)
            )
            return spawn_zenoh(
                binary,
                session_ttl=session_ttl,
                max_sessions=max_sessions,
                max_session_memory=max_session_memory,
                extra_args=extra_args,
                timeout=timeout,
                startup_timeout=startup_timeout,
                prefix=DEFAULT_PREFIX if prefix is None else prefix,
            )
        server = ServerProcess(
            binary,
            session_ttl=session_ttl,
            max_sessions=max_sessions,
            max_session_memory=max_session_memory,
            extra_args=extra_args,
        )
        return connect_spawned(
            server,
            lambda: cls(server.address, timeout=timeout, native=transport == "native"),
            startup_timeout,
        )

    @staticmethod
    def in_process(*, max_sessions: int | None = None) -> BaseClient:
        """A client of the in-process engine: the same API, no server and no socket.

        The engine (``esa_client._native``) is esa-core compiled into this package: the
        server's update law, checks and typed errors, bit for bit, at a few microseconds
        per batch round trip. Its sessions live in this process only; use :meth:`spawn`
        or :meth:`connect` to share them across processes, machines or languages.

        Args:
            max_sessions: Live-session limit; None = the server's default (100,000).

        Returns:
            A client over :class:`~esa_client.transports.in_process.InProcessTransport`.
        """
        # Imported here: the extension module loads only for those who use it.
        from .transports.in_process import InProcessTransport

        transport = InProcessTransport(max_sessions=max_sessions)
        return BaseClient(transport, address="in-process", timeout=float("inf"))
