"""Stable-baselines3 drop-ins: ``ESAPPO``, ``ESASAC`` and ``ESATD3`` take ``esa=EsaConfig(...)``.

Switching a script to ESA is one import and one argument::

    from esa_client.sb3 import ESAPPO, EsaConfig

    model = ESAPPO("MlpPolicy", "InvertedPendulum-v5", esa=EsaConfig(amplitude=0.2))
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

# torch loads torch._dynamo (and triton) lazily at the first optimizer step; doing that while
# gRPC's threads serve a StepStream segfaulted in our tests, so it is loaded before any channel.
import torch._dynamo  # noqa: F401  (imported for its side effect)

from ..config import EsaConfig

if TYPE_CHECKING:
    from .ppo import ESAPPO
    from .sac import ESASAC
    from .td3 import ESATD3

_DROP_INS = {"ESAPPO": "ppo", "ESASAC": "sac", "ESATD3": "td3"}


def __getattr__(name: str) -> Any:
    """Imports a drop-in on first use, so this module imports without stable-baselines3."""
    if name not in _DROP_INS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{_DROP_INS[name]}"), name)


__all__ = ["ESAPPO", "ESASAC", "ESATD3", "EsaConfig"]
