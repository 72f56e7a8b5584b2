"""esa_client: Python client for the esa Extremum-Seeking Action selection service.

Quick start::

    from esa_client import EsaClient, SessionConfig

    with EsaClient.spawn() as client:  # starts a private esa-server
        batch = client.create_batch(SessionConfig(action_dim=1, dt=0.05, amplitude=0.2,
                                                  frequency=10.0, learning_rate=0.1), n=4)
        probes = batch.probe(actions, episode_starts)       # (4, 1)
        improved = batch.report(critic(observations, probes))  # (4, 1)

One class builds every client: ``EsaClient.connect(address, transport="grpc" | "native"
| "zenoh")`` for a running server (``shards=N`` over Zenoh), ``EsaClient.spawn(...)`` for a
private one, ``EsaClient.in_process()`` for esa-core in this process; the transports are
in :mod:`esa_client.transports`. ``ZenohEsaClient`` and ``ShardedEsaClient`` (extra
``esa-client[zenoh]``) are what ``transport="zenoh"`` returns; building them directly is
deprecated. Stable-baselines3 drop-ins live in :mod:`esa_client.sb3`, RLlib's in
:mod:`esa_client.rllib`, a gymnasium wrapper in :mod:`esa_client.wrappers`.
"""

from importlib import metadata as _metadata

from .base_client import BaseClient
from .client import EsaClient, TransportName
from .config import EsaConfig, SessionConfig
from .errors import (
    DeadlineExceeded,
    EsaError,
    InvalidArgument,
    ResourceExhausted,
    ServerUnavailable,
    SessionAlreadyExists,
    SessionNotFound,
    StatusCode,
    StepMismatch,
    Unauthenticated,
)
from .session import Session, SessionBatch, SessionState
from .transports.base import LinearCritic
from .transports.grpcio import TlsConfig

# Zenoh is an optional extra (esa-client[zenoh]): its clients load on first use.
_ZENOH_EXPORTS = {"ZenohEsaClient", "ShardedEsaClient"}


def __getattr__(name: str) -> object:
    """Imports the Zenoh clients lazily, so that the package works without eclipse-zenoh."""
    if name in _ZENOH_EXPORTS:
        from . import zenoh_client

        return getattr(zenoh_client, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "BaseClient",
    "DeadlineExceeded",
    "EsaClient",
    "EsaConfig",
    "EsaError",
    "InvalidArgument",
    "LinearCritic",
    "ResourceExhausted",
    "ServerUnavailable",
    "Session",
    "SessionAlreadyExists",
    "SessionBatch",
    "SessionConfig",
    "SessionNotFound",
    "SessionState",
    "ShardedEsaClient",
    "StatusCode",
    "StepMismatch",
    "TlsConfig",
    "TransportName",
    "Unauthenticated",
    "ZenohEsaClient",
]

try:
    # One version source: the Cargo workspace's version, which maturin writes into the metadata.
    __version__: str = _metadata.version("esa-client")
except _metadata.PackageNotFoundError:  # pragma: no cover - imported from a bare source tree
    __version__ = "0+unknown"
