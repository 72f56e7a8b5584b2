"""Where the env runners' ESA sessions live: in each runner's process, or a given server."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, cast

from ..client import EsaClient
from ..common.runtime import OnUnavailable, check_on_unavailable
from ..reconnect import DEFAULT_RECONNECT_TIMEOUT, check_reconnect_timeout


@dataclass(frozen=True)
class EsaService:
    """Where the EnvRunners' sessions live (the ``service`` of :func:`~esa_client.rllib.with_esa`).

    With neither ``address`` nor ``zenoh``, each EnvRunner keeps its sessions in its own
    process (``EsaClient.in_process()``); servers given by either are yours to start.

    Args:
        address: A running server over gRPC, ``host:port`` or ``unix:/path``, reachable
            from every node that runs env runners.
        zenoh: Zenoh endpoint(s) of a server started with ``--zenoh`` (or of a router
            reaching it), e.g. ``"tcp/10.0.0.5:7447"``.
        shards: With ``zenoh``: N servers started with ``--shard i/N``; each session lives
            on the shard its id hashes to.
        zenoh_prefix: The servers' ``--zenoh-prefix`` (None: the client's default).
        token_file: A file holding the servers' auth token (a path valid on every node);
            None falls back to ``$ESA_AUTH_TOKEN`` in the runner's environment.
        timeout: Deadline of every call, in seconds.
        startup_timeout: Seconds to wait for a server at ``address`` to be ready.
        reconnect_timeout: Seconds a runner's batch keeps retrying a lost server before
            ``on_unavailable`` applies.
        on_unavailable: ``"raise"`` (default): the runner's step raises
            ``ServerUnavailable`` after one more reconnection; ``"skip"``: its envs execute
            the sampled actions until an episode starts, where the server is tried again
            (``env_runners/esa/unavailable_steps``).
    """

    address: str | None = None
    zenoh: str | Sequence[str] | None = None
    shards: int | None = None
    zenoh_prefix: str | None = None
    token_file: str | None = None
    timeout: float = 5.0
    startup_timeout: float = 60.0
    reconnect_timeout: float = DEFAULT_RECONNECT_TIMEOUT
    on_unavailable: OnUnavailable = "raise"

    def __post_init__(self) -> None:
        """Checks that the fields describe one kind of service."""
        if self.address is not None and self.zenoh is not None:
            raise ValueError(
                f"expected address or zenoh, got both ({self.address!r}, {self.zenoh!r})"
            )
        if self.shards is not None and (self.zenoh is None or self.shards < 1):
            raise ValueError(f"expected shards >= 1 together with zenoh, got {self.shards!r}")
        if not self.timeout > 0 or not self.startup_timeout > 0:
            raise ValueError(
                f"expected timeout and startup_timeout > 0, got {self.timeout}, "
                f"{self.startup_timeout}"
            )
        check_reconnect_timeout(self.reconnect_timeout)
        check_on_unavailable(self.on_unavailable)
        if self.zenoh is not None and not isinstance(self.zenoh, str):
            object.__setattr__(self, "zenoh", tuple(self.zenoh))

    @property
    def in_process(self) -> bool:
        """True when each runner keeps its sessions in its own process."""
        return self.address is None and self.zenoh is None

    def connect(self, wait: float | None = None) -> EsaClient:
        """A client of this service for the calling process, checked (the caller closes it).

        Args:
            wait: Seconds to wait for the servers to answer (default: ``startup_timeout``).

        Raises:
            ServerUnavailable: If no server answers within ``wait`` seconds.
            Unauthenticated: If a server refuses the token.
        """
        if self.in_process:
            return EsaClient.in_process()
        zenoh: dict[str, Any] = {}
        if self.zenoh is not None:
            zenoh = {"transport": "zenoh", "shards": self.shards, "prefix": self.zenoh_prefix}
        client = EsaClient.connect(
            self.zenoh if self.zenoh is not None else cast(str, self.address),
            timeout=self.timeout,
            token_file=self.token_file,
            check=False,
            reconnect_timeout=self.reconnect_timeout,
            **zenoh,
        )
        try:
            client.check(self.startup_timeout if wait is None else wait)
        except BaseException:
            client.close()
            raise
        return client

    def check(self) -> None:
        """Checks from this process, within ``timeout``, that the servers answer and take the token.

        Raises:
            ServerUnavailable: If no server answers.
            Unauthenticated: If a server refuses the token.
        """
        if not self.in_process:
            self.connect(self.timeout).close()
