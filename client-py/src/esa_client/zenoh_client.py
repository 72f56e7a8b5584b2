"""The clients over Zenoh: one server, or N shards of sessions.

Built by ``EsaClient.connect(..., transport="zenoh")`` and
``EsaClient.spawn(transport="zenoh")`` (:class:`esa_client.EsaClient`). Both have the
client API of :class:`~esa_client.base_client.BaseClient` (sessions, ``SessionBatch``,
typed errors, a deadline on every call); only the transport differs:
:class:`~esa_client.transports.zenoh_query.ZenohTransport` to one key prefix, or a
:class:`~esa_client.transports.sharded.ShardedTransport` over one per shard. Each client
owns its Zenoh session and the servers it spawned.
"""

from __future__ import annotations

import contextlib
import os
import secrets
from collections.abc import Sequence
from typing import TypedDict

import zenoh

from .base_client import BaseClient, check_timeout, connect_spawned, resolve_token
from .errors import ServerUnavailable, StatusCode
from .sharding import shard_of, shard_prefix
from .sidecar import ServerProcess
from .transports.sharded import ShardedStub, ShardedTransport
from .transports.zenoh_query import (
    DEFAULT_PREFIX,
    ZenohTransport,
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


class _ZenohConnection:
    """The checked arguments and the open Zenoh session both clients start from."""

    def __init__(
        self,
        connect: str | Sequence[str],
        prefix: str,
        timeout: float,
        config: zenoh.Config | None,
        token: str | None,
        token_file: str | os.PathLike[str] | None,
    ) -> None:
        self.timeout = check_timeout(timeout)
        endpoints = _endpoints(connect)
        self.address = ",".join(endpoints)
        self.prefix = check_prefix(prefix)
        self.token = resolve_token(token, token_file)
        config = config if config is not None else peer_config(endpoints, self.timeout)
        self.session = open_session(config, self.address)

    def close(self) -> None:
        """Closes the Zenoh session (already closed is fine)."""
        with contextlib.suppress(zenoh.ZError):
            self.session.close()

    def transport(self, prefix: str) -> ZenohTransport:
        """A transport to the servers serving ``prefix`` on this session."""
        return ZenohTransport(self.session, prefix, self.timeout, self.token)


def _spawn_zenoh_server(
    binary: str | os.PathLike[str] | None,
    args: Sequence[str],
    limits: _Limits,
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
            StatusCode.UNAVAILABLE,
        )
    return server, locators


class _Limits(TypedDict):
    """The server limits every spawned process gets (``ServerProcess`` arguments)."""

    session_ttl: float | None
    max_sessions: int | None
    max_session_memory: int | None


def _limits(
    session_ttl: float | None, max_sessions: int | None, max_session_memory: int | None
) -> _Limits:
    return {
        "session_ttl": session_ttl,
        "max_sessions": max_sessions,
        "max_session_memory": max_session_memory,
    }


class ZenohEsaClient(BaseClient):
    """A connection to an esa server over Zenoh, with the :class:`EsaClient` API.

    .. deprecated::
        Constructing it directly (``ZenohEsaClient(...)``, ``ZenohEsaClient.spawn()``) is
        kept for one release: use ``EsaClient.connect(endpoint, transport="zenoh")`` and
        ``EsaClient.spawn(transport="zenoh")``, which return this class.

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
        stub: The :class:`~esa_client.transports.zenoh_query.ZenohStub`.
        transport: The :class:`~esa_client.transports.zenoh_query.ZenohTransport`.
        server: The spawned :class:`~esa_client.sidecar.ServerProcess`, else None.
    """

    transport: ZenohTransport

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
        zenoh_link = _ZenohConnection(connect, prefix, timeout, config, token, token_file)
        try:
            transport = zenoh_link.transport(zenoh_link.prefix)
            super().__init__(transport, address=zenoh_link.address, timeout=zenoh_link.timeout)
            self.on_close(zenoh_link.close)
            self.prefix = zenoh_link.prefix
            self.stub = transport.stub
            if wait_ready:
                self.wait_ready(self.timeout)
        except BaseException:
            zenoh_link.close()
            raise

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

    def __repr__(self) -> str:
        """Shows the endpoints and prefix."""
        return f"{type(self).__name__}({self.address!r}, prefix={self.prefix!r})"


class ShardedEsaClient(BaseClient):
    """N esa servers (``--shard i/N``) behind one :class:`EsaClient` API.

    .. deprecated::
        Constructing it directly (``ShardedEsaClient(...)``, ``ShardedEsaClient.spawn()``)
        is kept for one release: use ``EsaClient.connect(endpoints, transport="zenoh",
        shards=N)`` and ``EsaClient.spawn(transport="zenoh", shards=N)``, which return
        this class.

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
        prefix: The key prefix.
        stub: The :class:`~esa_client.transports.sharded.ShardedStub` (the raw wire API).
        transport: The :class:`~esa_client.transports.sharded.ShardedTransport`.
        servers: The spawned server processes, ``servers[i]`` serving shard i.
    """

    transport: ShardedTransport

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
        zenoh_link = _ZenohConnection(connect, prefix, timeout, config, token, token_file)
        try:
            parts = [
                zenoh_link.transport(shard_prefix(zenoh_link.prefix, i)) for i in range(shards)
            ]
            transport = ShardedTransport(parts)
            super().__init__(transport, address=zenoh_link.address, timeout=zenoh_link.timeout)
            self.on_close(zenoh_link.close)
            self.shards = shards
            self.prefix = zenoh_link.prefix
            self.servers: list[ServerProcess] = []
            self.stub = ShardedStub([part.stub for part in parts])
            if wait_ready:
                self.wait_ready(self.timeout)
        except BaseException:
            zenoh_link.close()
            raise

    def shard_of(self, session_id: str) -> int:
        """The shard that owns ``session_id``."""
        return shard_of(session_id, self.shards)

    @classmethod
    def spawn(
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
        client: ShardedEsaClient | None = None
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
            for server in servers:
                client.on_close(server.stop)
            for i, server in enumerate(servers):
                client._wait_shard(i, server, startup_timeout)
        except BaseException:
            if client is not None:
                client.close()
            for server in servers:
                server.stop()
            raise
        return client

    def _wait_shard(self, shard: int, server: ServerProcess, timeout: float) -> None:
        server.check_running()
        if not self.transport.parts[shard].healthy(timeout, wait_for_ready=True):
            server.check_running()
            raise ServerUnavailable(
                f"shard {shard} ({server.binary}) not answering within {timeout} s; "
                f"its output:\n{server.output_tail()}",
                StatusCode.UNAVAILABLE,
            )

    def __repr__(self) -> str:
        """Shows the endpoints, prefix and shard count."""
        return f"ShardedEsaClient({self.address!r}, prefix={self.prefix!r}, shards={self.shards})"
