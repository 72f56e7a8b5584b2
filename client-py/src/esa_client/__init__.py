"""esa_client: Python client for the esa Extremum-Seeking Action selection service.

Quick start::

    from esa_client import EsaClient, SessionConfig

    with EsaClient.spawn() as client:  # starts a private esa-server
        batch = client.create_batch(SessionConfig(action_dim=1, dt=0.05, amplitude=0.2,
                                                  frequency=10.0, learning_rate=0.1), n=4)
        probes = batch.probe(actions, episode_starts)       # (4, 1)
        improved = batch.report(critic(observations, probes))  # (4, 1)

Stable-baselines3 drop-ins live in :mod:`esa_client.sb3`, a gymnasium wrapper in
:mod:`esa_client.wrappers`, and an in-process implementation of the update law in
:mod:`esa_client.reference`. ``ZenohEsaClient`` and ``ShardedEsaClient`` (extra
``esa-client[zenoh]``) offer the same API over Zenoh, for one server or N shards.
"""

from .client import EsaClient
from .config import EsaConfig, SessionConfig
from .errors import (
    DeadlineExceeded,
    EsaError,
    InvalidArgument,
    ResourceExhausted,
    ServerUnavailable,
    SessionAlreadyExists,
    SessionNotFound,
    StepMismatch,
    Unauthenticated,
)
from .grpc_transport import TlsConfig
from .session import Session, SessionBatch, SessionState

# Zenoh is an optional extra (esa-client[zenoh]): its clients load on first use.
_ZENOH_EXPORTS = {"ZenohEsaClient", "ShardedEsaClient"}


def __getattr__(name: str) -> object:
    """Imports the Zenoh clients lazily, so that the package works without eclipse-zenoh."""
    if name in _ZENOH_EXPORTS:
        from . import zenoh_client

        return getattr(zenoh_client, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "DeadlineExceeded",
    "EsaClient",
    "EsaConfig",
    "EsaError",
    "InvalidArgument",
    "ResourceExhausted",
    "ServerUnavailable",
    "Session",
    "SessionAlreadyExists",
    "SessionBatch",
    "SessionConfig",
    "SessionNotFound",
    "SessionState",
    "ShardedEsaClient",
    "StepMismatch",
    "TlsConfig",
    "Unauthenticated",
    "ZenohEsaClient",
]

__version__ = "0.1.0"
