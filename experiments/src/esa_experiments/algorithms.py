"""Method name -> model constructor, with hyperparameters from ``configs/algorithms.toml``.

A method is an algorithm family (``ppo``, ``sac``, ``td3``, ``ddpg``) plus an
exploration add-on: none, ESA (``esa_client.sb3``), adaptive parameter noise
(:mod:`esa_experiments.param_noise`), Ornstein-Uhlenbeck action noise (DDPG) or pink
action noise (TD3; Eberhard et al., ICLR 2023). TD3 always explores with action noise,
Gaussian unless the method says pink; its ESA arms add ESA on top of that noise.

ESA methods use one preset, the same on every env (no per-env tuning): ``default`` is
the shipped ``EsaConfig()`` (the PPO family's), ``off_policy`` the off-policy family's
``EsaConfig.off_policy()``, ``null`` the PPO default with learning rate 0 (the shift
stays 0: it isolates what the data handling alone does), ``sine`` the off-policy default
with learning rate 0 (with ``esa_execute='probe'``: exploration by the sinusoid alone),
``paper`` ``EsaConfig.paper()`` and ``target`` the PPO target mode's setting (picked by
``target_search`` on InvertedPendulum-v5 tuning seeds). A method's ``options`` are
further drop-in arguments: the gradient controls (``esa_shift='gradient'``: the same
bound, normalisation and gate, the shift along the critic's action gradient) and the
target mode.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np
from stable_baselines3 import DDPG, PPO, SAC, TD3
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.noise import NormalActionNoise, OrnsteinUhlenbeckActionNoise
from stable_baselines3.common.type_aliases import GymEnv

from esa_experiments.configs import algorithm_hyperparams, lookup
from esa_experiments.param_noise import PPOParamNoise, SACParamNoise


@dataclass(frozen=True)
class Method:
    """A trainable method.

    Attributes:
        label: name in plots and tables.
        family: algorithm family (table name in ``algorithms.toml``).
        addon: ``none``, ``esa``, ``param_noise``, ``ou`` or ``pink``.
        esa: the ESA preset of an ESA method (see :func:`esa_preset`).
        options: further keyword arguments of the ESA drop-in.
    """

    label: str
    family: str
    addon: str
    esa: str = ""
    options: tuple[tuple[str, Any], ...] = ()

    @property
    def off_policy(self) -> bool:
        """True for replay-buffer methods (they get smaller step budgets)."""
        return self.family in ("sac", "td3", "ddpg")


METHODS: dict[str, Method] = {
    "ppo": Method("PPO", "ppo", "none"),
    "ppo_esa": Method("PPO+ESA", "ppo", "esa", "default"),
    "ppo_esa_null": Method("PPO+ESA (lr 0)", "ppo", "esa", "null"),
    "ppo_esa_paper": Method("PPO+ESA (paper law)", "ppo", "esa", "paper"),
    "ppo_paramnoise": Method("PPO+ParamNoise", "ppo", "param_noise"),
    "ppo_qgrad": Method("PPO+gradient", "ppo", "esa", "default", (("esa_shift", "gradient"),)),
    "ppo_esa_target": Method("PPO+ESA target", "ppo", "esa", "target", (("esa_mode", "target"),)),
    "ppo_qgrad_target": Method(
        "PPO+gradient target",
        "ppo",
        "esa",
        "target",
        (("esa_mode", "target"), ("esa_shift", "gradient")),
    ),
    "sac": Method("SAC", "sac", "none"),
    "sac_esa": Method("SAC+ESA", "sac", "esa", "off_policy"),
    "sac_qgrad": Method("SAC+gradient", "sac", "esa", "off_policy", (("esa_shift", "gradient"),)),
    "sac_paramnoise": Method("SAC+ParamNoise", "sac", "param_noise"),
    "td3": Method("TD3", "td3", "none"),
    "td3_esa": Method("TD3+ESA", "td3", "esa", "off_policy"),
    "td3_sine": Method("TD3+sine", "td3", "esa", "sine", (("esa_execute", "probe"),)),
    "td3_qgrad": Method("TD3+gradient", "td3", "esa", "off_policy", (("esa_shift", "gradient"),)),
    "td3_pink": Method("TD3+pink noise", "td3", "pink"),
    "ddpg_ou": Method("DDPG+OU", "ddpg", "ou"),
}

LABELS = {name: method.label for name, method in METHODS.items()}
"""Method name -> display name."""

BASELINE_OF = {
    "ppo_esa": "ppo",
    "ppo_esa_null": "ppo",
    "ppo_esa_paper": "ppo",
    "ppo_qgrad": "ppo",
    "ppo_esa_target": "ppo",
    "ppo_qgrad_target": "ppo",
    "sac_esa": "sac",
    "sac_qgrad": "sac",
    "td3_esa": "td3",
    "td3_sine": "td3",
    "td3_qgrad": "td3",
    "td3_pink": "td3",
}
"""Which method an ESA method is compared with (returns and wall-clock overhead)."""


GRADIENT_CONTROL_OF = {
    "ppo_esa": "ppo_qgrad",
    "ppo_esa_target": "ppo_qgrad_target",
    "sac_esa": "sac_qgrad",
    "td3_esa": "td3_qgrad",
}
"""The gradient control of an ESA method: ESC is credited only where it beats it."""

TARGET_TRUST_REGION = 1.0
TARGET_WEIGHT = 0.03
"""The PPO target mode's bound (policy stds) and loss weight (``target_search``)."""


def esa_preset(name: str) -> dict[str, Any]:
    """The ``EsaConfig`` fields of an ESA preset (see the module docstring).

    Resolved from ``esa_client`` itself, so a run's fingerprint changes (and the run
    is redone) whenever the shipped default changes.
    """
    from esa_client import EsaConfig

    presets = {
        "default": EsaConfig(),
        "null": EsaConfig(learning_rate=0.0),
        "paper": EsaConfig.paper(),
        "off_policy": EsaConfig.off_policy(),
        "sine": EsaConfig.off_policy(learning_rate=0.0),
        "target": EsaConfig(trust_region=TARGET_TRUST_REGION),
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
        hp["esa_options"] = dict(spec.options)
        if spec.esa == "target":
            hp["esa_options"]["esa_target_weight"] = TARGET_WEIGHT
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
    if spec.family == "td3":
        kwargs["action_noise"] = _td3_noise(env, spec.addon, hp.pop("noise_sigma"), seed)
    if spec.addon == "esa":
        from esa_client import EsaConfig
        from esa_client.sb3 import ESAPPO, ESASAC, ESATD3

        cls = _of_family({"ppo": ESAPPO, "sac": ESASAC, "td3": ESATD3}, spec.family)
        kwargs["esa"] = EsaConfig(**hp.pop("esa"))
        if spec.family == "ppo":
            # The runner gives each job a core (--jobs N fills N): a head-fit worker would
            # only compete with the other jobs and hold ~400 MB. Same bits either way.
            kwargs["esa_head_worker"] = False
        kwargs.update(hp.pop("esa_options", {}))
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
        cls = _of_family({"ppo": PPO, "sac": SAC, "td3": TD3}, spec.family)
    return cls("MlpPolicy", env, **kwargs, **hp)


def _td3_noise(env: GymEnv, addon: str, sigma: float, seed: int) -> Any:
    """TD3's exploration noise: Gaussian, or pink over one episode's length."""
    dim = int(np.prod(env.action_space.shape or ()))
    if addon != "pink":
        return NormalActionNoise(mean=np.zeros(dim), sigma=sigma * np.ones(dim))
    from pink import PinkActionNoise

    spec = env.get_attr("spec")[0] if hasattr(env, "get_attr") else env.spec
    horizon = (spec.max_episode_steps if spec is not None else None) or 1000
    return PinkActionNoise(sigma, horizon, dim, rng=np.random.default_rng(seed))
