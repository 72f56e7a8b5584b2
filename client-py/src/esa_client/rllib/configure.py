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

from ..common.controls import Control, check_control
from ..config import EsaConfig
from .connector import ConnectorFactory
from .learners import EsaPPOTorchLearner, EsaSACTorchLearner
from .modules import EsaPPOTorchRLModule, EsaSACTorchRLModule
from .service import EsaService


def _ours(current: Any, default: type[Any], ours: type[Any], what: str) -> type[Any]:
    """``ours`` in place of RLlib's ``default``, or ``current`` if it subclasses ``ours``."""
    if current is default:
        return ours
    if isinstance(current, type) and issubclass(current, ours):
        return current
    raise ValueError(
        f"expected RLlib's default {what} or a subclass of {ours.__name__}, got {current!r}"
    )


def with_esa(
    config: Any,
    *,
    esa: EsaConfig | None = None,
    service: EsaService | None = None,
    budget: int | None = None,
    control: Control | None = None,
) -> Any:
    """Adds ESA to an RLlib ``SACConfig`` or ``PPOConfig`` (new API stack, torch); returns it.

    RLlib then runs what ``ESAPPO`` and ``ESASAC`` ship (docs/guides/rllib.md). Call it after
    setting the environment, model and ``normalize_actions``; change none of them afterwards.

    Args:
        config: A ``SACConfig`` or ``PPOConfig`` (changed in place, like RLlib's own setters).
        esa: The ESA hyperparameters, in the module's action units (ESAPPO's and ESASAC's).
            Default: ``EsaConfig.ppo()`` for PPO, ``EsaConfig.off_policy()`` for SAC.
        service: Where the sessions live (default: in each runner's process); checked here.
        budget: The env steps you will train for; needed with a fade, a fraction of them.
        control: None (ESA), ``"placebo"`` or ``"gradient"``: the drop-ins' ``esa_control``.

    Raises:
        ValueError: For another algorithm, the old API stack, a framework other than
            torch, a multi-agent setup, a custom RLModule or learner class that is not
            one of ours (or a subclass), a fade without a budget, or a bad setting.
        ServerUnavailable: If the service's servers do not answer from this process.
        Unauthenticated: If they refuse the token.
    """
    is_sac = isinstance(config, SACConfig)
    if not is_sac and not isinstance(config, PPOConfig):
        raise ValueError(f"expected a SACConfig or PPOConfig, got {type(config).__name__}")
    if esa is None:
        esa = EsaConfig.off_policy() if is_sac else EsaConfig.ppo()
    if not isinstance(esa, EsaConfig):
        raise ValueError(f"expected esa to be an EsaConfig, got {esa!r}")
    if budget is not None and (
        isinstance(budget, bool) or not isinstance(budget, int) or budget < 1
    ):
        raise ValueError(f"expected budget a number of env steps >= 1, got {budget!r}")
    if esa.fade is not None and budget is None:
        raise ValueError(
            f"expected budget= the env steps you will train for (EsaConfig(fade={esa.fade}) "
            "fades ESA over that fraction of them), got None; or pass an EsaConfig with "
            "fade=None"
        )
    control = check_control(control)
    service = service if service is not None else EsaService()
    if not isinstance(service, EsaService):
        raise ValueError(f"expected service to be an EsaService, got {service!r}")
    if not (config.enable_rl_module_and_learner and config.enable_env_runner_and_connector_v2):
        raise ValueError("expected RLlib's new API stack (RLModule, Learner, ConnectorV2)")
    if config.framework_str != "torch":
        raise ValueError(f"expected framework 'torch', got {config.framework_str!r}")
    if config.is_multi_agent:
        raise ValueError("expected a single-agent config: ESA for RLlib is single-agent")
    service.check()  # a wrong address or token fails here, not on the runners
    # Plain data: the module reads it on every node, from model_config.
    settings = {
        "config": dataclasses.asdict(esa),
        "budget": budget,
        "normalize_actions": bool(config.normalize_actions),
    }

    spec = config.rl_module_spec
    if is_sac:
        module = _ours(spec.module_class, DefaultSACTorchRLModule, EsaSACTorchRLModule, "RLModule")
        learner = _ours(config.learner_class, SACTorchLearner, EsaSACTorchLearner, "learner")
    else:
        module = _ours(spec.module_class, DefaultPPOTorchRLModule, EsaPPOTorchRLModule, "RLModule")
        learner = _ours(config.learner_class, PPOTorchLearner, EsaPPOTorchLearner, "learner")
    # A spec's model_config may be a dict or a DefaultModelConfig dataclass: keep either.
    given = spec.model_config
    if dataclasses.is_dataclass(given) and not isinstance(given, type):
        given = dataclasses.asdict(given)
    model_config = {**(given if isinstance(given, dict) else {}), "esa": settings}
    config.rl_module(
        rl_module_spec=RLModuleSpec(
            module_class=module, catalog_class=spec.catalog_class, model_config=model_config
        )
    )
    config.learners(learner_class=learner)
    previous = getattr(config, "_module_to_env_connector", None)
    if isinstance(previous, ConnectorFactory):
        previous = previous.previous  # calling with_esa twice replaces the first
    factory = ConnectorFactory(previous, esa=esa, service=service, control=control)
    config.env_runners(module_to_env_connector=factory)
    return config
