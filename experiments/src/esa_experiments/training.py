"""One reinforcement-learning run: build env and model, train with periodic evaluation.

Shared by every RL study. A run's
``RunSpec.config`` holds everything (``total_steps``, ``eval_every``,
``eval_episodes``, ``hyperparams``), so the run is reproducible from its sidecar.

A run whose hyperparameters say ``normalize`` (RL Zoo3's ``normalize: true``, the
``ppo_zoo`` arm of study ``zoo_baselines``) trains on a ``VecNormalize`` of its envs
(observations and rewards, discounted with the run's ``gamma``, SB3's defaults otherwise:
what the zoo does). Its evaluation sees the observations normalized with the training
statistics as they are at that moment, never updated by evaluation
(:class:`FrozenNormalization`), and the env's own rewards: its returns are the env's, like
every other run's.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import VecEnv, VecNormalize

from esa_experiments.algorithms import build_model, get_method, resolve_hyperparams
from esa_experiments.evaluation import EvalSettings, ProgressFn, train_and_evaluate
from esa_experiments.runs import RunResult, RunSpec
from esa_experiments.tasks import get_task


@dataclass(frozen=True)
class StepBudget:
    """Environment steps of one run, by algorithm kind.

    Attributes:
        on_policy: steps of PPO-family runs.
        off_policy: steps of SAC/DDPG runs (about 10x slower per step on CPU).
        eval_every_on: evaluation interval of on-policy runs.
        eval_every_off: evaluation interval of off-policy runs.
        eval_episodes: deterministic episodes per evaluation.
        overrides: per algorithm family (``ppo``, ``sac``, ``ddpg``), values
            replacing ``algorithms.toml`` ones; the smoke budgets use it for
            rollouts and warm-ups that fit their few steps.
    """

    on_policy: int
    off_policy: int
    eval_every_on: int
    eval_every_off: int
    eval_episodes: int
    overrides: dict[str, dict[str, Any]] = field(default_factory=dict)


SMOKE_BUDGET = StepBudget(
    on_policy=256,
    off_policy=300,
    eval_every_on=128,
    eval_every_off=150,
    eval_episodes=1,
    # Two PPO rollouts of 4 envs x 32 steps (ESAPPO probes from the second one on)
    # and a short off-policy warm-up.
    overrides={
        "ppo": {"n_steps": 32, "batch_size": 64, "n_epochs": 2},
        "sac": {"learning_starts": 100, "batch_size": 64},
        "td3": {"learning_starts": 100, "batch_size": 64},
        "ddpg": {"learning_starts": 100, "batch_size": 64},
    },
)
"""The CI-sized budget of the RL studies (``--budget smoke``)."""


def rl_spec(
    study: str,
    env: str,
    method: str,
    seed: int,
    budget_name: str,
    budget: StepBudget,
    *,
    variant: str | None = None,
    esa_overrides: dict[str, Any] | None = None,
) -> RunSpec:
    """The spec of one RL run with its hyperparameters resolved from the config files.

    Args:
        study: study name.
        env: task key.
        method: method name (see :mod:`esa_experiments.algorithms`).
        seed: seed.
        budget_name: ``smoke`` or ``full``.
        budget: the step budget.
        variant: name under which the run is stored instead of ``method``
            (ablation variants of one method).
        esa_overrides: ESA fields replacing the config file's.
    """
    get_task(env)
    kind = get_method(method)
    off = kind.off_policy
    hyperparams = {
        **resolve_hyperparams(method, env, esa_overrides),
        **budget.overrides.get(kind.family, {}),
    }
    config = {
        "method": method,
        "total_steps": budget.off_policy if off else budget.on_policy,
        "eval_every": budget.eval_every_off if off else budget.eval_every_on,
        "eval_episodes": budget.eval_episodes,
        "hyperparams": hyperparams,
        "uses_server": kind.addon == "esa",
    }
    return RunSpec(study, env, variant or method, seed, budget_name, config)


class FrozenNormalization(gym.ObservationWrapper[np.ndarray, np.ndarray, np.ndarray]):
    """The evaluation env of a normalized run: observations as its policy sees them in training.

    Each observation is normalized with ``stats``' running mean and variance as they are when
    it comes (``VecNormalize.normalize_obs``, which updates nothing); rewards pass unchanged.
    RL Zoo3 evaluates the same way (a copy of the training statistics, not trained, rewards
    not normalized).

    Args:
        env: the evaluation env.
        stats: the training envs' ``VecNormalize``.
    """

    def __init__(self, env: gym.Env[np.ndarray, np.ndarray], stats: VecNormalize) -> None:
        """Wraps ``env``."""
        super().__init__(env)
        self.stats = stats

    def observation(self, observation: np.ndarray) -> np.ndarray:
        """The observation normalized with the training statistics of now."""
        normalized = self.stats.normalize_obs(observation)
        assert isinstance(normalized, np.ndarray)
        return normalized


@contextlib.contextmanager
def trained(spec: RunSpec, progress: ProgressFn) -> Iterator[tuple[RunResult, BaseAlgorithm]]:
    """Trains the run's model and yields its result and the trained model.

    The result holds the evaluation table, the training log (SB3 logger values:
    ESA and parameter-noise statistics, losses) as the extra table ``log``, and
    the mean of each ``esa/`` and ``param_noise/`` statistic in the sidecar.

    Everything (envs, ESA server) is closed when the block exits. With ``normalize`` the
    envs are normalized (see the module docstring).
    """
    config = spec.config
    hyperparams = config["hyperparams"]
    task = get_task(spec.env)
    env: VecEnv = make_vec_env(task.make, n_envs=hyperparams.get("n_envs", 1), seed=spec.seed)
    eval_env: gym.Env[Any, Any] = task.make()
    if hyperparams.get("normalize"):
        stats = VecNormalize(env, gamma=hyperparams["gamma"])
        env, eval_env = stats, FrozenNormalization(eval_env, stats)
    model: BaseAlgorithm | None = None
    try:
        model = build_model(config["method"], env, spec.seed, config["hyperparams"])
        settings = EvalSettings(every=config["eval_every"], episodes=config["eval_episodes"])
        frame, log = train_and_evaluate(
            model, config["total_steps"], eval_env, settings, spec.seed, progress
        )
        means = {
            f"mean {key}": float(log[key].mean())
            for key in log.columns
            if key.startswith(("esa/", "param_noise/")) or key == "train/approx_kl"
        }
        yield RunResult(frame, means, {"log": log}), model
    finally:
        if model is not None and hasattr(model, "esa_close"):
            model.esa_close()
        env.close()
        eval_env.close()


def run_training(spec: RunSpec, progress: ProgressFn) -> RunResult:
    """Trains and evaluates one run (the ``run`` of studies that need nothing more)."""
    with trained(spec, progress) as (result, _):
        return result
