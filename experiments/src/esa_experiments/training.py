"""One reinforcement-learning run: build env and model, train with periodic evaluation.

Shared by every RL study. A run's
``RunSpec.config`` holds everything (``total_steps``, ``eval_every``,
``eval_episodes``, ``hyperparams``), so the run is reproducible from its sidecar.

A run whose hyperparameters say ``normalize`` (RL Zoo3's ``normalize: true``, the
``ppo_zoo`` arm of study ``zoo_baselines``) trains on a ``VecNormalize`` of its envs, and
is evaluated as :mod:`esa_client.compare.training` says (the code ``esa-compare`` runs).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

from esa_client.compare import training as compare_training
from esa_client.compare.evaluation import EvalSettings, ProgressFn
from stable_baselines3.common.base_class import BaseAlgorithm

from esa_experiments.algorithms import build_model, get_method, resolve_hyperparams
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


@contextlib.contextmanager
def trained(spec: RunSpec, progress: ProgressFn) -> Iterator[tuple[RunResult, BaseAlgorithm]]:
    """Trains the run's model and yields its result and the trained model.

    The result holds the evaluation table, the training log (SB3 logger values:
    ESA and parameter-noise statistics, losses) as the extra table ``log``, and
    the mean of each ``esa/`` and ``param_noise/`` statistic in the sidecar.

    Everything (envs, ESA server) is closed when the block exits
    (:func:`esa_client.compare.training.trained`).
    """
    config = spec.config
    hyperparams = config["hyperparams"]
    with compare_training.trained(
        get_task(spec.env).make,
        lambda env: build_model(config["method"], env, spec.seed, hyperparams),
        seed=spec.seed,
        n_envs=hyperparams.get("n_envs", 1),
        normalize={} if hyperparams.get("normalize") else None,
        gamma=hyperparams.get("gamma", 0.99),
        total_steps=config["total_steps"],
        settings=EvalSettings(every=config["eval_every"], episodes=config["eval_episodes"]),
        progress=progress,
    ) as trained_run:
        yield trained_run


def run_training(spec: RunSpec, progress: ProgressFn) -> RunResult:
    """Trains and evaluates one run (the ``run`` of studies that need nothing more)."""
    with trained(spec, progress) as (result, _):
        return result
