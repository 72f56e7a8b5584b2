"""The client API every transport shares: sessions, batches, restoring lost sessions, health.

:class:`BaseClient` is written against :class:`~esa_client.transports.base.Transport`
only, and owns the transport it is given (and whatever it registered to release with it:
a Zenoh session, the servers it spawned). Which transport, and how to open it, is the
business of :class:`~esa_client.EsaClient`'s constructors (:mod:`esa_client.client`).
"""

from __future__ import annotations

import contextlib
import os
import time
import uuid
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TypeVar

from ._proto.esa.v1 import esa_pb2
from .config import SessionConfig
from .errors import EsaError, ServerUnavailable, StatusCode
from .reconnect import DEFAULT_RECONNECT_TIMEOUT, Reconnect
from .session import Session, SessionBatch, restore_sessions
from .sidecar import ServerProcess
from .state import SessionState, as_batch_configs
from .transports.base import Transport


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
    """The session API over a :class:`~esa_client.transports.base.Transport` the client owns.

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
        reconnect_timeout: How long a batch keeps retrying when the server is unreachable
            (down, restarting, stalled, or the connection or stream broke), in seconds,
            before it raises ``ServerUnavailable``; 0 raises the first failure. Set by
            ``connect``/``spawn`` (default 60); read by :meth:`create_batch`.
    """

    def __init__(self, transport: Transport, *, address: str, timeout: float) -> None:
        """Takes ownership of ``transport``."""
        self.transport = transport
        self.address = address
        self.timeout = timeout
        self.server: ServerProcess | None = None
        self.sessions_restored = 0
        self.reconnect_timeout = DEFAULT_RECONNECT_TIMEOUT
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
                    StatusCode.UNAVAILABLE,
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

        The batch rides out a lost server for up to :attr:`reconnect_timeout` seconds:
        it repeats the failed step with capped exponential backoff and jitter; once the
        server answers again, it sends what the server has not applied (by the
        sessions' step numbers, so no report is applied twice) and recreates sessions a
        restarted server lost, which then start a new episode (losing that episode's
        shift, the episode count and the response's mean square).

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
            reconnect=Reconnect(self.address, self.reconnect_timeout, closed=lambda: self._closed),
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
