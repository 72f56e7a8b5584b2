"""ESA for Ray RLlib (new API stack, torch): SAC and PPO, env runners on many nodes.

Install with ``pip install "esa-client[rllib]"``. One call adds ESA to a config::

    from ray.rllib.algorithms.sac import SACConfig
    from esa_client import EsaConfig
    from esa_client.rllib import with_esa

    config = (
        SACConfig()
        .environment("Pendulum-v1")
        .env_runners(num_env_runners=2, num_envs_per_env_runner=2)
    )
    algo = with_esa(config, esa=EsaConfig.off_policy()).build_algo()
    algo.train()

Without ``esa=`` SAC gets ``EsaConfig.off_policy()``, ESASAC's default, and PPO
``EsaConfig()``: RLlib's PPO has ESAPPO's quadratic head but neither its fade nor its
decoupled objective, so ``EsaConfig.ppo()`` (which fades) is not its default.

Every env copy of every EnvRunner gets its own ESA session. The env executes, and the
episode stores, Algorithm 1's action ``a_t + v(t)`` (PPO: unclipped, with its exact
behaviour log-probability ``log pi_old(a_t)``); the critic is probed on the env runners
(SAC: the target twins, kept in the env runners' module and synced with the learner's;
PPO: ESAPPO's quadratic head, fitted on the learner and synced the same way). By default
each runner keeps its sessions in its own process (:class:`EsaService`);
``EsaService(address=...)`` or ``EsaService(zenoh=..., shards=N)`` use a shared or sharded
server instead (``deploy/README.md``).

Pieces: :func:`with_esa`, :class:`EsaService`,
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
