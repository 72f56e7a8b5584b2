"""esa_client: Python client for the esa Extremum-Seeking Action selection service.

``EsaClient.connect(address)`` reaches a running server, ``EsaClient.spawn()`` a private one
and ``EsaClient.in_process()`` esa-core in this process, each with the same session API
(``docs/guides/client.md``). Stable-baselines3 drop-ins live in :mod:`esa_client.sb3`,
RLlib's in :mod:`esa_client.rllib`, gymnasium wrappers in :mod:`esa_client.wrappers` and
:mod:`esa_client.vector_wrapper`.
"""

from importlib import metadata as _metadata

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
from .session import Session, SessionBatch, SessionProgress, SessionState
from .transports.base import LinearCritic, QuadraticCritic
from .transports.grpc import TlsConfig

__all__ = [
    "DeadlineExceeded",
    "EsaClient",
    "EsaConfig",
    "EsaError",
    "InvalidArgument",
    "LinearCritic",
    "QuadraticCritic",
    "ResourceExhausted",
    "ServerUnavailable",
    "Session",
    "SessionAlreadyExists",
    "SessionBatch",
    "SessionConfig",
    "SessionNotFound",
    "SessionProgress",
    "SessionState",
    "StatusCode",
    "StepMismatch",
    "TlsConfig",
    "TransportName",
    "Unauthenticated",
]

try:
    # One version source: the Cargo workspace's version, which maturin writes into the metadata.
    __version__: str = _metadata.version("esa-client")
except _metadata.PackageNotFoundError:  # pragma: no cover - imported from a bare source tree
    __version__ = "0+unknown"
