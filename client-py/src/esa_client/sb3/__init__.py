"""Stable-baselines3 drop-ins: ``ESASAC`` and ``ESAPPO`` take ``esa=EsaConfig(...)``.

Switching a script to ESA is one import and one argument::

    from esa_client.sb3 import ESAPPO, EsaConfig

    model = ESAPPO("MlpPolicy", "InvertedPendulum-v5", esa=EsaConfig(amplitude=0.2))
"""

# torch loads torch._dynamo (and triton's native libraries) lazily at the first optimizer
# step; doing that while gRPC's threads serve an open StepStream segfaulted in our SB3
# tests, so it is loaded here, before any channel exists.
import torch._dynamo  # noqa: F401  (imported for its side effect)

from ..config import EsaConfig
from .ppo import ESAPPO
from .sac import ESASAC

__all__ = ["ESAPPO", "ESASAC", "EsaConfig"]
