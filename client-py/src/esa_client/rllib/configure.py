"""``with_esa``: one call that turns an RLlib SAC or PPO config into its ESA version."""

from __future__ import annotations

import dataclasses
from typing import Any

from ray.rllib.algorithms.ppo import PPOConfig
from ray.rllib.algorithms.ppo.torch.default_ppo_torch_rl_module import DefaultPPOTorchRLModule
from ray.rllib.algorithms.ppo.torch.ppo_torch_learner import PPOTorchLearner
from ray.rllib.algorithms.sac import SACConfig
from ray.rllib.algorithms.sac.torch.default_sac_torch_rl_module import DefaultSACTorchRLModule
from ray.rllib.algorithms.sac.torch.sac_torch_learner import SACTorchLearner
from ray.rllib.core.rl_module.rl_module import RLModuleSpec

from ..config import EsaConfig
from .connector import ConnectorFactory
from .learners import EsaPPOTorchLearner, EsaSACTorchLearner
from .modules import PROBE_CRITICS, EsaPPOTorchRLModule, EsaSACTorchRLModule
from .service import EsaService


def _positive_int(name: str, value: object) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"expected {name} an integer >= 1, got {value!r}")
    return value


def with_esa(
    config: Any,
    *,
    esa: EsaConfig | None = None,
    service: EsaService | None = None,
    probe_critic: str = "target_mean",
    gate_every: int = 1000,
    head_hidden: int = 64,
    head_learning_rate: float = 1e-3,
    head_epochs: int = 5,
    head_batch_size: int = 256,
    head_rollouts: int = 4,
    record_shift: bool = False,
    improvement_every: int = 8,
) -> Any:
    """Adds ESA to an RLlib ``SACConfig`` or ``PPOConfig`` (new API stack, torch); returns it.

    Sets the RLModule (:class:`~esa_client.rllib.modules.EsaSACTorchRLModule` /
    :class:`~esa_client.rllib.modules.EsaPPOTorchRLModule`: RLlib's default module
    whose env-runner copy keeps the critic ESA probes), the learner
    (:class:`~esa_client.rllib.learners.EsaSACTorchLearner` /
    :class:`~esa_client.rllib.learners.EsaPPOTorchLearner`: the gate, and PPO's
    quadratic head) and appends :class:`~esa_client.rllib.connector.EsaModuleToEnv` to
    the module-to-env connectors (after yours). Call it after setting the environment,
    model and ``normalize_actions``; change none of these three afterwards.

    :mod:`esa_client.rllib` shows an example.

    Args:
        config: A ``SACConfig`` or ``PPOConfig`` (changed in place, like RLlib's own
            setters).
        esa: The ESA hyperparameters, in the module's action units: with RLlib's default
            ``normalize_actions=True``, the Box scaled to [-1, 1] (PPO) or SAC's squashed
            [-1, 1], the units ESAPPO and ESASAC use. Default: ``EsaConfig.off_policy()``
            for SAC and ``EsaConfig()`` for PPO, as for ``ESASAC`` and ``ESAPPO``.
        service: Where the sessions live (default: in each runner's process).
        probe_critic: SAC: the critic ESA probes, as ``ESASAC``'s ``esa_probe_critic``.
        gate_every: SAC: sampled env steps between two gate checks.
        head_hidden: PPO: hidden units of each of the quadratic head's two layers.
        head_learning_rate: PPO: Adam learning rate of the head.
        head_epochs: PPO: passes over its data each time the head is fitted.
        head_batch_size: PPO: minibatch size when fitting the head.
        head_rollouts: PPO: how many of the latest train batches the head is fitted on.
        record_shift: Store the applied shift with each step (extra model output
            ``esa_shift``), for diagnostics.
        improvement_every: Measure ``esa/improvement`` on one env-runner step in this many.

    Returns:
        ``config``.

    Raises:
        ValueError: For another algorithm, the old API stack, a framework other than
            torch, a multi-agent setup, a custom RLModule or learner class that is not
            one of ours (or a subclass), or a bad setting.
        ServerUnavailable: If the service's servers do not answer from this process.
        Unauthenticated: If they refuse the token.
    """
    if esa is None:
        esa = EsaConfig.off_policy() if isinstance(config, SACConfig) else EsaConfig()
    if not isinstance(esa, EsaConfig):
        raise ValueError(f"expected esa to be an EsaConfig, got {esa!r}")
    if esa.fade is not None:
        raise ValueError(
            f"expected EsaConfig(fade=None) with RLlib (its runners do not know the training "
            f"budget a fade is a fraction of), got fade={esa.fade!r}"
        )
    service = service if service is not None else EsaService()
    if not isinstance(service, EsaService):
        raise ValueError(f"expected service to be an EsaService, got {service!r}")
    # Here, not on the runners: a wrong address or token fails before anything starts.
    service.check()
    module_class: type[Any]
    default_module: type[Any]
    learner_class: type[Any]
    default_learner: type[Any]
    if isinstance(config, SACConfig):
        module_class, default_module = EsaSACTorchRLModule, DefaultSACTorchRLModule
        learner_class, default_learner = EsaSACTorchLearner, SACTorchLearner
    elif isinstance(config, PPOConfig):
        module_class, default_module = EsaPPOTorchRLModule, DefaultPPOTorchRLModule
        learner_class, default_learner = EsaPPOTorchLearner, PPOTorchLearner
    else:
        raise ValueError(f"expected a SACConfig or PPOConfig, got {type(config).__name__}")
    if not (config.enable_rl_module_and_learner and config.enable_env_runner_and_connector_v2):
        raise ValueError("expected RLlib's new API stack (RLModule, Learner, ConnectorV2)")
    if config.framework_str != "torch":
        raise ValueError(f"expected framework 'torch', got {config.framework_str!r}")
    if config.is_multi_agent:
        raise ValueError("expected a single-agent config: ESA for RLlib is single-agent")
    if probe_critic not in PROBE_CRITICS:
        raise ValueError(f"expected probe_critic in {PROBE_CRITICS}, got {probe_critic!r}")
    if not head_learning_rate > 0:
        raise ValueError(f"expected head_learning_rate > 0, got {head_learning_rate}")
    _positive_int("improvement_every", improvement_every)
    # Plain data: the module reads it on every node, from model_config.
    settings = {
        "config": dataclasses.asdict(esa),
        "probe_critic": probe_critic,
        "gate_every": _positive_int("gate_every", gate_every),
        "head_hidden": _positive_int("head_hidden", head_hidden),
        "head_learning_rate": float(head_learning_rate),
        "head_epochs": _positive_int("head_epochs", head_epochs),
        "head_batch_size": _positive_int("head_batch_size", head_batch_size),
        "head_rollouts": _positive_int("head_rollouts", head_rollouts),
        "normalize_actions": bool(config.normalize_actions),
    }

    spec = config.rl_module_spec
    current = spec.module_class
    if current is not default_module and not (
        isinstance(current, type) and issubclass(current, module_class)
    ):
        raise ValueError(
            f"expected RLlib's default RLModule or a subclass of {module_class.__name__}, "
            f"got {current!r}"
        )
    # A spec's model_config may be a dict or a DefaultModelConfig dataclass: keep either.
    given = spec.model_config
    model_config: dict[str, Any] = {}
    if isinstance(given, dict):
        model_config = dict(given)
    elif dataclasses.is_dataclass(given) and not isinstance(given, type):
        model_config = dataclasses.asdict(given)
    config.rl_module(
        rl_module_spec=RLModuleSpec(
            module_class=current if current is not default_module else module_class,
            catalog_class=spec.catalog_class,
            model_config={**model_config, "esa": settings},
        )
    )
    learner = config.learner_class
    if learner is not default_learner and not (
        isinstance(learner, type) and issubclass(learner, learner_class)
    ):
        raise ValueError(
            f"expected RLlib's default learner or a subclass of {learner_class.__name__}, "
            f"got {learner!r}"
        )
    config.learners(learner_class=learner if learner is not default_learner else learner_class)
    previous = getattr(config, "_module_to_env_connector", None)
    if isinstance(previous, ConnectorFactory):
        previous = previous.previous  # calling with_esa twice replaces the first
    config.env_runners(
        module_to_env_connector=ConnectorFactory(
            previous,
            esa=esa,
            service=service,
            record_shift=record_shift,
            improvement_every=improvement_every,
        )
    )
    return config
