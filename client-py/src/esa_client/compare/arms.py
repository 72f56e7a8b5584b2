"""The arms as models, and the run a worker (a process or a Ray task) does with one.

The baseline is the plain SB3 algorithm; ``esa`` is its drop-in with the shipped default
(ESA in this process); ``placebo`` and ``gradient`` are the drop-in's controls
(``esa_control``). Every arm gets the same settings, envs, seeds and evaluation.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.noise import NormalActionNoise, OrnsteinUhlenbeckActionNoise
from stable_baselines3.common.vec_env import VecEnv

from esa_client.compare.evaluation import EvalSettings, ProgressFn
from esa_client.compare.hyperparams import Hyperparams, algorithm_kwargs
from esa_client.compare.runs import RunFolder, RunResult, RunSpec
from esa_client.compare.training import env_factory, trained

_CONTROL = {"baseline": None, "esa": None, "placebo": "placebo", "gradient": "gradient"}


def _classes(algo: str) -> tuple[Callable[..., BaseAlgorithm], Callable[..., BaseAlgorithm]]:
    """The plain SB3 class and its ESA drop-in."""
    from stable_baselines3 import PPO, SAC, TD3

    from esa_client.sb3 import ESAPPO, ESASAC, ESATD3

    classes: dict[str, tuple[Callable[..., BaseAlgorithm], Callable[..., BaseAlgorithm]]] = {
        "ppo": (PPO, ESAPPO),
        "sac": (SAC, ESASAC),
        "td3": (TD3, ESATD3),
    }
    return classes[algo]


def _action_noise(spec: dict[str, Any], env: VecEnv) -> Any:
    """The zoo's ``noise_type``/``noise_std`` as SB3 action noise for the env's actions."""
    dim = int(np.prod(env.action_space.shape or (1,)))
    mean, sigma = np.zeros(dim), float(spec["std"]) * np.ones(dim)
    if spec["type"] == "normal":
        return NormalActionNoise(mean, sigma)
    if spec["type"] == "ornstein-uhlenbeck":
        return OrnsteinUhlenbeckActionNoise(mean, sigma)
    raise ValueError(f"expected noise_type normal or ornstein-uhlenbeck, got {spec['type']!r}")


def build_model(arm: str, algo: str, env: VecEnv, seed: int, params: Hyperparams) -> BaseAlgorithm:
    """The arm's model on ``env``, untrained."""
    plain, drop_in = _classes(algo)
    kwargs = algorithm_kwargs(params)
    if "action_noise" in kwargs:
        kwargs["action_noise"] = _action_noise(kwargs["action_noise"], env)
    if arm == "baseline":
        return plain(params.policy, env, seed=seed, verbose=0, **kwargs)
    return drop_in(
        params.policy,
        env,
        seed=seed,
        verbose=0,
        esa=params.esa or None,
        esa_control=_CONTROL[arm],
        **kwargs,
    )


@dataclass(frozen=True)
class CompareJob:
    """The :class:`~esa_client.compare.execution.Job` of ``esa-compare``'s runs.

    Attributes:
        out: the comparison's folder.
    """

    out: Path

    def folder(self, spec: RunSpec) -> RunFolder:
        """The comparison's folder."""
        return RunFolder(self.out)

    def prepare(self) -> None:
        """Imports SB3 and the drop-ins."""
        _classes("ppo")

    def run(self, spec: RunSpec, progress: ProgressFn) -> RunResult:
        """Trains and evaluates one arm on one seed."""
        return run_arm(spec, progress)


def run_arm(spec: RunSpec, progress: ProgressFn) -> RunResult:
    """Trains and evaluates one arm on one seed, as the spec's config says."""
    config = spec.config
    params = Hyperparams(**config["hyperparams"])
    with trained(
        env_factory(config["env"]),
        lambda env: build_model(spec.method, config["algo"], env, spec.seed, params),
        seed=spec.seed,
        n_envs=params.n_envs,
        normalize=params.normalize,
        gamma=float(params.kwargs.get("gamma", 0.99)),
        total_steps=config["total_steps"],
        settings=EvalSettings(every=config["eval_every"], episodes=config["eval_episodes"]),
        progress=progress,
    ) as (result, _):
        return result
