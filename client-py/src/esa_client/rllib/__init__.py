"""ESA for Ray RLlib (new API stack, torch): SAC and PPO, env runners on many nodes.

One call adds ESA to a config: ``with_esa(PPOConfig()..., budget=1_000_000)`` (the RLlib
guide, ``docs/guides/rllib.md``, has the whole example). RLlib then runs what the SB3
drop-ins ship: PPO ``ESAPPO``'s method (``EsaConfig.ppo()``, its quadratic head, its
decoupled objective, ESA faded over the first half of the budget), SAC ``ESASAC``'s. Every
env copy of every EnvRunner gets its own session,
kept in the runner's process by default (:class:`EsaService`), or on a shared or sharded
server. Needs the ``rllib`` extra. Pieces: :func:`with_esa`, :class:`EsaService`,
:class:`EsaModuleToEnv` (the module-to-env ConnectorV2), :class:`EsaSACTorchRLModule`,
:class:`EsaPPOTorchRLModule`, :class:`EsaSACTorchLearner`, :class:`EsaPPOTorchLearner`.
"""

from __future__ import annotations

import importlib
from typing import Any

# Ray is imported on first use of an RLlib piece, so that esa_client.rllib.service works
# without it.
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
    if name == "EsaConfig":
        from ..config import EsaConfig

        return EsaConfig
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
