"""Evaluation of a training run at fixed step intervals.

Every ``every`` environment steps (and at step 0 and at the end) the policy is
run deterministically, without any exploration machinery (no ESA, no
parameter or action noise: just ``model.policy``), for ``episodes`` episodes on
a separate evaluation env whose episode ``i`` is reset with seed
``seed + i``: every evaluation of every method sees the same initial states.

Training wall-clock (``train_seconds``) and the training process's CPU time
(``train_cpu_seconds``; a spawned esa-server's own CPU is not included) are
measured without evaluation time, so they are comparable across methods (the
ESA overhead ratio). On a shared machine the CPU time is the steadier one.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
import pandas as pd
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import KVWriter, Logger

ProgressFn = Callable[[int], None]
"""Called with the number of environment steps done so far."""

EVAL_SEED_OFFSET = 10_000
"""Evaluation env seeds start here (+ run seed) so they never equal training seeds."""


@dataclass(frozen=True)
class EvalSettings:
    """How a run is evaluated.

    Attributes:
        every: environment steps between two evaluations.
        episodes: deterministic episodes per evaluation.
    """

    every: int
    episodes: int

    def __post_init__(self) -> None:
        """Rejects non-positive settings."""
        if self.every < 1 or self.episodes < 1:
            raise ValueError(
                "expected every >= 1 and episodes >= 1, "
                f"got every={self.every}, episodes={self.episodes}"
            )


@contextlib.contextmanager
def noise_free(model: BaseAlgorithm) -> Iterator[None]:
    """Runs the body with ``model``'s unperturbed policy (for evaluation).

    A model that perturbs its policy's parameters to explore has an ``unperturbed()``
    context manager that suspends the perturbation; any other model is left untouched.
    """
    suspend = getattr(model, "unperturbed", None)
    with suspend() if suspend is not None else contextlib.nullcontext():
        yield


def run_episodes(
    model: BaseAlgorithm, env: gym.Env, episodes: int, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """Runs ``model.policy`` deterministically; returns per-episode returns and lengths."""
    returns = np.zeros(episodes)
    lengths = np.zeros(episodes, dtype=int)
    with noise_free(model):
        for i in range(episodes):
            obs, _ = env.reset(seed=seed + i)
            done = False
            while not done:
                action, _ = model.policy.predict(obs, deterministic=True)
                obs, reward, terminated, truncated, _ = env.step(action)
                returns[i] += float(reward)
                lengths[i] += 1
                done = terminated or truncated
    return returns, lengths


class PeriodicEvaluation(BaseCallback):
    """SB3 callback recording deterministic evaluation returns every ``settings.every`` steps.

    Args:
        eval_env: the evaluation env (not the training env).
        settings: interval and number of episodes.
        seed: run seed; evaluation episodes use ``EVAL_SEED_OFFSET + seed + i``.
        progress: optional callback receiving the step count as training goes.
    """

    def __init__(
        self,
        eval_env: gym.Env,
        settings: EvalSettings,
        seed: int,
        progress: ProgressFn | None = None,
    ) -> None:
        """Sets up an empty evaluation table."""
        super().__init__()
        self.eval_env = eval_env
        self.settings = settings
        self.eval_seed = EVAL_SEED_OFFSET + seed
        self.progress = progress
        self.rows: list[dict[str, float]] = []
        self._next_eval = 0
        self._train_seconds = 0.0
        self._train_cpu_seconds = 0.0
        self._eval_seconds = 0.0
        self._since = 0.0
        self._cpu_since = 0.0
        # Training episodes so far: count, those that ended by termination (a crash:
        # the fall, flip or exit of the env, not its time limit), summed return and length.
        self._episodes = {"train_episodes": 0, "train_crashes": 0}
        self._sums = {"train_return_sum": 0.0, "train_length_sum": 0.0}

    def _evaluate(self) -> None:
        self._train_seconds += time.perf_counter() - self._since
        self._train_cpu_seconds += time.process_time() - self._cpu_since
        start = time.perf_counter()
        returns, lengths = run_episodes(
            self.model, self.eval_env, self.settings.episodes, self.eval_seed
        )
        self._eval_seconds += time.perf_counter() - start
        self.rows.append(
            {
                "step": self.num_timesteps,
                "return_mean": float(returns.mean()),
                "return_std": float(returns.std()),
                "length_mean": float(lengths.mean()),
                "train_seconds": self._train_seconds,
                "train_cpu_seconds": self._train_cpu_seconds,
                "eval_seconds": self._eval_seconds,
                **self._episodes,
                **self._sums,
            }
        )
        self._next_eval = self.num_timesteps + self.settings.every
        self._since = time.perf_counter()
        self._cpu_since = time.process_time()

    def _on_training_start(self) -> None:
        self._since = time.perf_counter()
        self._cpu_since = time.process_time()
        self._evaluate()

    def _count_episodes(self) -> None:
        """Adds the training episodes that ended this step (Monitor's ``episode`` info)."""
        for done, info in zip(
            self.locals.get("dones", ()), self.locals.get("infos", ()), strict=True
        ):
            episode = info.get("episode") if done else None
            if episode is None:
                continue
            self._episodes["train_episodes"] += 1
            self._episodes["train_crashes"] += int(not info.get("TimeLimit.truncated", False))
            self._sums["train_return_sum"] += float(episode["r"])
            self._sums["train_length_sum"] += float(episode["l"])

    def _on_step(self) -> bool:
        self._count_episodes()
        if self.num_timesteps >= self._next_eval:
            self._evaluate()
        if self.progress is not None:
            self.progress(self.num_timesteps)
        return True

    def _on_training_end(self) -> None:
        if self.rows[-1]["step"] < self.num_timesteps:
            self._evaluate()

    def frame(self) -> pd.DataFrame:
        """The evaluation table: one row per evaluation."""
        return pd.DataFrame(self.rows)


LOGGED_PREFIXES = ("esa/", "param_noise/", "train/", "rollout/")
"""SB3 logger keys kept in a run's training log."""


class LogCapture(KVWriter):
    """An SB3 logger output that keeps the logged values (ESA and noise statistics)."""

    def __init__(self) -> None:
        """Starts with no rows."""
        self.rows: list[dict[str, float]] = []

    def write(
        self,
        key_values: dict[str, Any],
        key_excluded: dict[str, tuple[str, ...]],
        step: int = 0,
    ) -> None:
        """Keeps the numeric values of the interesting keys of one dump."""
        row = {
            key: float(value)
            for key, value in key_values.items()
            if key.startswith(LOGGED_PREFIXES) and isinstance(value, (int, float, np.number))
        }
        if row:
            self.rows.append({"step": step, **row})

    def close(self) -> None:
        """Nothing to release."""

    def frame(self) -> pd.DataFrame:
        """One row per logger dump (just a ``step`` column if nothing was logged)."""
        return pd.DataFrame(self.rows) if self.rows else pd.DataFrame({"step": []})


def train_and_evaluate(
    model: BaseAlgorithm,
    total_steps: int,
    eval_env: gym.Env,
    settings: EvalSettings,
    seed: int,
    progress: ProgressFn | None = None,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Trains ``model`` with periodic evaluation; returns the evaluation table and training log.

    Args:
        model: the model to train.
        total_steps: environment steps.
        eval_env: the evaluation env.
        settings: evaluation interval and episodes.
        seed: run seed (selects the evaluation seeds).
        progress: optional step-count callback.
    """
    callback = PeriodicEvaluation(eval_env, settings, seed, progress)
    log = LogCapture()
    model.set_logger(Logger(folder=None, output_formats=[log]))
    model.learn(total_timesteps=total_steps, callback=callback)
    return callback.frame(), log.frame()
