"""ESA for Ray RLlib (new API stack, torch): SAC and PPO, env runners on many nodes.

``with_esa(config, budget=...)`` adds ESA to a config (``docs/guides/rllib.md``); needs the
``rllib`` extra.
"""

from __future__ import annotations

import importlib
from typing import Any

from ..config import EsaConfig

# Ray is imported on first use of an RLlib piece: esa_client.rllib.service works without it.
_EXPORTS = {
    "ESA_OBS": "modules",
    "ESA_SHIFT": "connector",
    "EsaModuleToEnv": "connector",
    "EsaPPOTorchLearner": "learners",
    "EsaPPOTorchRLModule": "modules",
    "EsaSACTorchLearner": "learners",
    "EsaSACTorchRLModule": "modules",
    "EsaService": "service",
    "with_esa": "configure",
}


def __getattr__(name: str) -> Any:
    """Imports the pieces lazily (RLlib ones need ``pip install 'esa-client[rllib]'``)."""
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    if _EXPORTS[name] != "service":
        try:
            import ray.rllib  # noqa: F401
        except ImportError as err:
            raise ImportError(
                f"esa_client.rllib.{name} needs Ray RLlib: pip install 'esa-client[rllib]'"
            ) from err
    return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)


__all__ = ["EsaConfig", *sorted(_EXPORTS)]
