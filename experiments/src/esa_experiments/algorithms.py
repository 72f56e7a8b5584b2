"""Method name -> model constructor, with hyperparameters from ``configs/algorithms.toml``.

A method is an algorithm family (``ppo``, ``sac``, ``ddpg``) plus an
exploration add-on: none, ESA (``esa_client.sb3``), adaptive parameter noise
(:mod:`esa_experiments.param_noise`) or Ornstein-Uhlenbeck action noise.

ESA methods use one of three presets, the same on every env (no per-env tuning):
``default`` is the shipped ``EsaConfig()``, ``null`` the same wiring with learning
rate 0 (the shift stays 0: it isolates what the data handling alone does), and
``paper`` is ``EsaConfig.paper()``, the paper's law and settings.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np
from stable_baselines3 import DDPG, PPO, SAC
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.noise import OrnsteinUhlenbeckActionNoise
from stable_baselines3.common.type_aliases import GymEnv

from esa_experiments.configs import algorithm_hyperparams, lookup
from esa_experiments.param_noise import PPOParamNoise, SACParamNoise


@dataclass(frozen=True)
class Method:
    """A trainable method.

    Attributes:
        label: name in plots and tables.
        family: algorithm family (table name in ``algorithms.toml``).
        addon: ``none``, ``esa``, ``param_noise`` or ``ou``.
        esa: the ESA preset of an ESA method (see :func:`esa_preset`).
    """

    label: str
    family: str
    addon: str
    esa: str = ""

    @property
    def off_policy(self) -> bool:
        """True for replay-buffer methods (they get smaller step budgets)."""
        return self.family in ("sac", "ddpg")


METHODS: dict[str, Method] = {
    "ppo": Method("PPO", "ppo", "none"),
    "ppo_esa": Method("PPO+ESA", "ppo", "esa", "default"),
    "ppo_esa_null": Method("PPO+ESA (lr 0)", "ppo", "esa", "null"),
    "ppo_esa_paper": Method("PPO+ESA (paper law)", "ppo", "esa", "paper"),
    "ppo_paramnoise": Method("PPO+ParamNoise", "ppo", "param_noise"),
    "sac": Method("SAC", "sac", "none"),
    "sac_esa": Method("SAC+ESA", "sac", "esa", "default"),
    "sac_paramnoise": Method("SAC+ParamNoise", "sac", "param_noise"),
    "ddpg_ou": Method("DDPG+OU", "ddpg", "ou"),
}

LABELS = {name: method.label for name, method in METHODS.items()}
"""Method name -> display name."""

BASELINE_OF = {
    "ppo_esa": "ppo",
    "ppo_esa_null": "ppo",
    "ppo_esa_paper": "ppo",
    "sac_esa": "sac",
}
"""Which method an ESA method is compared with (returns and wall-clock overhead)."""


def esa_preset(name: str) -> dict[str, Any]:
    """The ``EsaConfig`` fields of an ESA preset (``default``, ``null`` or ``paper``).

    Resolved from ``esa_client`` itself, so a run's fingerprint changes (and the run
    is redone) whenever the shipped default changes.
    """
    from esa_client import EsaConfig

    presets = {
        "default": EsaConfig(),
        "null": EsaConfig(learning_rate=0.0),
        "paper": EsaConfig.paper(),
    }
    return dataclasses.asdict(lookup(presets, name, "an ESA preset"))


def get_method(name: str) -> Method:
    """Returns the method called ``name``.

    Raises:
        ValueError: for an unknown name (the message lists the known ones).
    """
    return lookup(METHODS, name, "a method")


def resolve_hyperparams(
    method: str, env: str, esa_overrides: dict[str, Any] | None = None
) -> dict[str, Any]:
    """All hyperparameters of ``method`` on ``env``, as stored in the run's sidecar.

    Args:
        method: method name.
        env: task key (selects the per-env tables of the config files).
        esa_overrides: ESA fields replacing those of the method's preset (ablations).
    """
    spec = get_method(method)
    hp = algorithm_hyperparams(spec.family, env)
    if spec.addon != "param_noise":
        hp.pop("param_noise", None)
    if spec.addon == "esa":
        hp["esa"] = {**esa_preset(spec.esa), **(esa_overrides or {})}
    elif esa_overrides:
        raise ValueError(f"expected ESA overrides only for ESA methods, got them for {method!r}")
    return hp


def _of_family(classes: dict[str, type[BaseAlgorithm]], family: str) -> type[BaseAlgorithm]:
    return classes[family]


def build_model(method: str, env: GymEnv, seed: int, hyperparams: dict[str, Any]) -> BaseAlgorithm:
    """Constructs the SB3 model of ``method`` on ``env`` (CPU, no logging output).

    Args:
        method: method name.
        env: training env (a gymnasium env or an SB3 VecEnv).
        seed: model seed.
        hyperparams: output of :func:`resolve_hyperparams`.
    """
    spec = get_method(method)
    cls: type[BaseAlgorithm]
    hp = dict(hyperparams)
    hp.pop("n_envs", None)  # used to build the env (see training.py)
    kwargs: dict[str, Any] = {
        "policy_kwargs": {"net_arch": hp.pop("net_arch")},
        "seed": seed,
        "device": "cpu",
        "verbose": 0,
    }
    if spec.addon == "esa":
        from esa_client import EsaConfig
        from esa_client.sb3 import ESAPPO, ESASAC

        cls = _of_family({"ppo": ESAPPO, "sac": ESASAC}, spec.family)
        kwargs["esa"] = EsaConfig(**hp.pop("esa"))
    elif spec.addon == "param_noise":
        cls = _of_family({"ppo": PPOParamNoise, "sac": SACParamNoise}, spec.family)
        kwargs["param_noise"] = hp.pop("param_noise")
    elif spec.addon == "ou":
        dim = int(np.prod(env.action_space.shape or ()))
        kwargs["action_noise"] = OrnsteinUhlenbeckActionNoise(
            mean=np.zeros(dim),
            sigma=hp.pop("ou_sigma") * np.ones(dim),
            theta=hp.pop("ou_theta"),
        )
        cls = DDPG
    else:
        cls = _of_family({"ppo": PPO, "sac": SAC}, spec.family)
    return cls("MlpPolicy", env, **kwargs, **hp)
