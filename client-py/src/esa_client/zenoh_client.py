"""Clients that reach esa servers over Zenoh: one server, or N shards of sessions.

Both have the :class:`~esa_client.EsaClient` API (sessions, ``SessionBatch``,
typed errors, a deadline on every call, ``spawn``); only the wire differs.
"""

from __future__ import annotations

import contextlib
import os
import secrets
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor

import grpc
import zenoh

from .client import EsaClient, connect_spawned, resolve_token
from .errors import ServerUnavailable
from .sharding import BatchTransport, ShardedBatchTransport, ShardedStub, shard_of, shard_prefix
from .sidecar import ServerProcess
from .transport import UnaryTransport
from .zenoh_transport import (
    DEFAULT_PREFIX,
    StepQueryTransport,
    ZenohStub,
    check_prefix,
    open_session,
    peer_config,
)

_LOCATOR_LINE = "zenoh listening on "


def _endpoints(connect: str | Sequence[str]) -> tuple[str, ...]:
    endpoints = (connect,) if isinstance(connect, str) else tuple(connect)
    for endpoint in endpoints:
        if "/" not in endpoint:
            raise ValueError(
                f"expected a Zenoh endpoint like 'tcp/127.0.0.1:7447', got {endpoint!r}"
            )
    return endpoints


def _spawn_zenoh_server(
    binary: str | os.PathLike[str] | None,
    args: Sequence[str],
    limits: dict[str, float | None],
    token: str,
    startup_timeout: float,
) -> tuple[ServerProcess, list[str]]:
    """Starts ``esa-server --zenoh`` (Zenoh on loopback, gRPC on a private socket).

    Zenoh listens on a loopback TCP port that every local user can reach, so the server
    requires ``token`` on every query (and gRPC call).
    """
    server = ServerProcess(binary, **limits, token=token, extra_args=["--zenoh", *args])
    try:
        locators = server.announced(_LOCATOR_LINE, startup_timeout)
    except BaseException:
        server.stop()
        raise
    if not locators:
        server.stop()
        raise ServerUnavailable(
            f"{server.binary} announced no Zenoh locator; its output:\n{server.output_tail()}",
            grpc.StatusCode.UNAVAILABLE,
        )
    return server, locators


class ZenohEsaClient(EsaClient):
    """A connection to an esa server over Zenoh, with the :class:`EsaClient` API.

    The client is a Zenoh peer that connects to ``connect`` only (no scouting, no
    listener) unless a full Zenoh ``config`` is given (e.g. client mode to a
    ``zenohd`` router). Every call is a query with the client's deadline: no answer
    in time raises ``DeadlineExceeded``, no server serving the key raises
    ``ServerUnavailable`` at once.

    Example::

        with ZenohEsaClient.spawn() as client:   # esa-server --zenoh on loopback
            batch = client.create_batch(config, n=8)
            probes = batch.probe(actions)

    Args:
        connect: Zenoh endpoint(s) of the server or router, e.g. ``tcp/127.0.0.1:7447``.
        prefix: The servers' ``--zenoh-prefix``.
        timeout: Deadline in seconds for every call (and for connecting).
        config: A complete Zenoh config to use instead of the peer config built
            from ``connect``.
        wait_ready: Wait (up to ``timeout``) until the server answers before returning.
        token: The auth token of servers started with ``--auth-token-file``, sent as
            every query's attachment.
        token_file: A file holding the token instead; with neither, ``ESA_AUTH_TOKEN``.

    Attributes:
        address: The endpoints, comma-separated (for messages).
        prefix: The key prefix.
        stub: The :class:`~esa_client.zenoh_transport.ZenohStub`.
        server: The spawned :class:`~esa_client.sidecar.ServerProcess`, else None.
    """

    def __init__(
        self,
        connect: str | Sequence[str] = "tcp/127.0.0.1:7447",
        *,
        prefix: str = DEFAULT_PREFIX,
        timeout: float = 5.0,
        config: zenoh.Config | None = None,
        wait_ready: bool = True,
        token: str | None = None,
        token_file: str | os.PathLike[str] | None = None,
    ) -> None:
        """Opens the Zenoh session and declares the queriers."""
        if not timeout > 0:
            raise ValueError(f"expected timeout > 0 seconds, got {timeout}")
        endpoints = _endpoints(connect)
        self.address = ",".join(endpoints)
        self.prefix = check_prefix(prefix)
        self.timeout = float(timeout)
        self._token = resolve_token(token, token_file)
        self.server: ServerProcess | None = None
        self.sessions_restored = 0
        self._closed = False
        config = config if config is not None else peer_config(endpoints, self.timeout)
        self._zenoh = open_session(config, self.address)
        try:
            self.stub = self._make_stub()
            if wait_ready:
                self.wait_ready(self.timeout)
        except BaseException:
            self._zenoh.close()
            raise

    def _make_stub(self) -> ZenohStub | ShardedStub:
        return ZenohStub(self._zenoh, self.prefix, self.timeout, self._token)

    def _stubs(self) -> tuple[ZenohStub, ...]:
        return (self.stub,)  # type: ignore[return-value]

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
        prefix: str = DEFAULT_PREFIX,
    ) -> ZenohEsaClient:
        """Starts ``esa-server --zenoh`` on loopback and connects to its announced locator.

        The server also serves gRPC on a private Unix socket (``client.server.address``),
        on the same sessions. It requires a fresh random token (``client.server.token``)
        on both, since its Zenoh port is open to every local user. It is stopped by
        :meth:`close`, or stops by itself if this process dies first.

        Args:
            binary: Path of the esa-server executable; None searches for it.
            session_ttl: Idle-session expiry in seconds (0 = never); None = the server's
                default (600).
            max_sessions: Live-session limit; None = the server's default.
            max_session_memory: Session memory budget in bytes; None = the server's default.
            extra_args: Further server arguments.
            timeout: Per-call deadline of the returned client.
            startup_timeout: Seconds to wait for the server to answer.
            prefix: The ``--zenoh-prefix`` to serve and use.

        Raises:
            ServerUnavailable: If the server exits or does not answer in time.
        """
        args = ["--zenoh-prefix", prefix, *extra_args]
        limits = _limits(session_ttl, max_sessions, max_session_memory)
        token = secrets.token_urlsafe(32)
        server, locators = _spawn_zenoh_server(binary, args, limits, token, startup_timeout)
        return connect_spawned(
            server,
            lambda: cls(locators, prefix=prefix, timeout=timeout, wait_ready=False, token=token),
            startup_timeout,
        )

    def healthy(self, *, timeout: float | None = None, wait_for_ready: bool = False) -> bool:
        """True if every server behind this client answers a query.

        Args:
            timeout: Bound per server in seconds (default: the client's timeout).
            wait_for_ready: Wait (up to the bound) for the servers' queryables to become
                reachable instead of failing at once when they are not.
        """
        bound = self.timeout if timeout is None else timeout
        return all(s.healthy(bound, wait_for_ready=wait_for_ready) for s in self._stubs())

    def batch_transport(
        self, ids: Sequence[str], action_dim: int, *, use_stream: bool = False
    ) -> BatchTransport:
        """Batches over the ``ProbeBatch`` / ``ReportBatch`` keys, or the ``StepStream`` key."""
        return _shard_transport(self.stub, self.timeout, use_stream)  # type: ignore[arg-type]

    def close(self) -> None:
        """Closes the Zenoh session and stops a spawned server. Idempotent."""
        if self._closed:
            return
        self._closed = True
        with contextlib.suppress(zenoh.ZError):
            self._zenoh.close()
        for server in self._servers():
            server.stop()

    def _servers(self) -> list[ServerProcess]:
        return [self.server] if self.server is not None else []

    def __repr__(self) -> str:
        """Shows the endpoints and prefix."""
        return f"{type(self).__name__}({self.address!r}, prefix={self.prefix!r})"


def _limits(
    session_ttl: float | None, max_sessions: int | None, max_session_memory: int | None
) -> dict[str, float | None]:
    return {
        "session_ttl": session_ttl,
        "max_sessions": max_sessions,
        "max_session_memory": max_session_memory,
    }


def _shard_transport(stub: ZenohStub, timeout: float, use_stream: bool) -> BatchTransport:
    return StepQueryTransport(stub) if use_stream else UnaryTransport(stub, timeout)  # type: ignore[arg-type]


class ShardedEsaClient(ZenohEsaClient):
    """N esa servers (``--shard i/N``) behind one :class:`EsaClient` API.

    A session lives on shard :func:`~esa_client.sharding.shard_of` ``(id, N)``; a
    ``SessionBatch`` splits every probe/report per shard, sends the parts
    concurrently and merges the answers in order. If a shard is down, calls for its
    sessions raise ``ServerUnavailable`` (naming the shard's keys) while the other
    shards keep serving.

    Args:
        connect: Zenoh endpoints reaching every shard (each server's locator, or a router).
        shards: N, the number of shards the servers were started with.
        prefix: The servers' ``--zenoh-prefix``.
        timeout: Deadline in seconds for every call (and for connecting).
        config: A complete Zenoh config instead of the peer config built from ``connect``.
        wait_ready: Wait (up to ``timeout``) until every shard answers before returning.
        token: The servers' auth token (sent as every query's attachment).
        token_file: A file holding the token instead; with neither, ``ESA_AUTH_TOKEN``.

    Attributes:
        shards: N.
        servers: The spawned server processes, ``servers[i]`` serving shard i.
    """

    def __init__(
        self,
        connect: str | Sequence[str],
        *,
        shards: int,
        prefix: str = DEFAULT_PREFIX,
        timeout: float = 5.0,
        config: zenoh.Config | None = None,
        wait_ready: bool = True,
        token: str | None = None,
        token_file: str | os.PathLike[str] | None = None,
    ) -> None:
        """Opens one Zenoh session and declares the queriers of every shard."""
        if shards < 1:
            raise ValueError(f"expected shards >= 1, got {shards}")
        self.shards = shards
        self.servers: list[ServerProcess] = []
        self._executor = ThreadPoolExecutor(max_workers=shards, thread_name_prefix="esa-shard")
        try:
            super().__init__(
                connect,
                prefix=prefix,
                timeout=timeout,
                config=config,
                wait_ready=wait_ready,
                token=token,
                token_file=token_file,
            )
        except BaseException:
            self._executor.shutdown()
            raise

    def _make_stub(self) -> ShardedStub:
        prefixes = [shard_prefix(self.prefix, i) for i in range(self.shards)]
        return ShardedStub([ZenohStub(self._zenoh, p, self.timeout, self._token) for p in prefixes])

    def _stubs(self) -> tuple[ZenohStub, ...]:
        return self.stub.shards  # type: ignore[union-attr]

    def shard_of(self, session_id: str) -> int:
        """The shard that owns ``session_id``."""
        return shard_of(session_id, self.shards)

    @classmethod
    def spawn(  # type: ignore[override]
        cls,
        binary: str | os.PathLike[str] | None = None,
        *,
        shards: int = 2,
        session_ttl: float | None = None,
        max_sessions: int | None = None,
        max_session_memory: int | None = None,
        extra_args: Sequence[str] = (),
        timeout: float = 5.0,
        startup_timeout: float = 30.0,
        prefix: str = DEFAULT_PREFIX,
    ) -> ShardedEsaClient:
        """Starts N local ``esa-server --zenoh --shard i/N`` processes and connects to all.

        Each also serves gRPC on its own private Unix socket (``client.servers[i].address``);
        all require one fresh random token (``client.servers[i].token``).

        Args:
            binary: Path of the esa-server executable; None searches for it.
            shards: N, the number of server processes.
            session_ttl: Idle-session expiry in seconds; None = the server's default.
            max_sessions: Live-session limit per shard; None = the server's default.
            max_session_memory: Session memory budget per shard in bytes; None = the
                server's default.
            extra_args: Further arguments for every server.
            timeout: Per-call deadline of the returned client.
            startup_timeout: Seconds to wait for each server to answer.
            prefix: The ``--zenoh-prefix`` to serve and use.
        """
        if shards < 1:
            raise ValueError(f"expected shards >= 1, got {shards}")
        servers: list[ServerProcess] = []
        locators: list[str] = []
        limits = _limits(session_ttl, max_sessions, max_session_memory)
        token = secrets.token_urlsafe(32)
        try:
            for i in range(shards):
                args = ["--zenoh-prefix", prefix, "--shard", f"{i}/{shards}", *extra_args]
                server, announced = _spawn_zenoh_server(
                    binary, args, limits, token, startup_timeout
                )
                servers.append(server)
                locators += announced
            client = cls(
                locators,
                shards=shards,
                prefix=prefix,
                timeout=timeout,
                wait_ready=False,
                token=token,
            )
            client.servers = servers
            for i, server in enumerate(servers):
                client._wait_shard(i, server, startup_timeout)
        except BaseException:
            for server in servers:
                server.stop()
            raise
        return client

    def _wait_shard(self, shard: int, server: ServerProcess, timeout: float) -> None:
        server.check_running()
        if not self._stubs()[shard].healthy(timeout, wait_for_ready=True):
            server.check_running()
            raise ServerUnavailable(
                f"shard {shard} ({server.binary}) not answering within {timeout} s; "
                f"its output:\n{server.output_tail()}",
                grpc.StatusCode.UNAVAILABLE,
            )

    def batch_transport(
        self, ids: Sequence[str], action_dim: int, *, use_stream: bool = False
    ) -> BatchTransport:
        """Batches split per shard and sent concurrently (see :mod:`esa_client.sharding`)."""
        parts = [_shard_transport(s, self.timeout, use_stream) for s in self._stubs()]
        return ShardedBatchTransport(parts, ids, action_dim, self._executor)

    def close(self) -> None:
        """Closes the Zenoh session, the worker threads and spawned servers. Idempotent."""
        if not self._closed:
            self._executor.shutdown()
        super().close()

    def _servers(self) -> list[ServerProcess]:
        return list(self.servers)

    def __repr__(self) -> str:
        """Shows the endpoints, prefix and shard count."""
        return f"ShardedEsaClient({self.address!r}, prefix={self.prefix!r}, shards={self.shards})"
