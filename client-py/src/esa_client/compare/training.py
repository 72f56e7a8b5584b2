"""One run: build the envs and the model, train with periodic evaluation, close everything.

Shared by ``esa-compare`` and the experiments' studies. A run whose settings ask for
``normalize`` (RL Zoo3's ``normalize: true``) trains on a ``VecNormalize`` of its envs
(observations and rewards, discounted with the run's ``gamma``: what the zoo does). Its
evaluation sees the observations normalized with the training statistics as they are at
that moment, never updated by evaluation (:class:`FrozenNormalization`), and the env's own
rewards: its returns are the env's, comparable with an unnormalized run's.
"""

from __future__ import annotations

import contextlib
import importlib
from collections.abc import Callable, Iterator
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import VecEnv, VecNormalize

from esa_client.compare.evaluation import EvalSettings, ProgressFn, train_and_evaluate
from esa_client.compare.runs import RunResult

EnvFactory = Callable[[], gym.Env[Any, Any]]
"""Makes one env (``gym.make`` of an id, or a user's ``module:factory``)."""


def env_factory(env: str) -> EnvFactory:
    """The maker of ``env``: a registered gymnasium id, or ``module:factory``.

    Raises:
        ValueError: if the module or the factory cannot be found, or the id is not registered.
    """
    if ":" in env:
        module_name, _, attribute = env.partition(":")
        try:
            module = importlib.import_module(module_name)
        except ImportError as err:
            raise ValueError(
                f"expected an importable module in --env {env!r}, got: {err}"
            ) from None
        factory = getattr(module, attribute, None)
        if not callable(factory):
            raise ValueError(f"expected a callable {attribute!r} in module {module_name}, got none")
        return factory  # type: ignore[no-any-return]
    try:
        gym.spec(env)
    except gym.error.Error as err:
        raise ValueError(
            "expected a registered gymnasium env id or module:factory for --env, "
            f"got {env!r}: {err}"
        ) from None
    return lambda: gym.make(env)


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


LOGGED_MEANS = ("esa/", "param_noise/")
"""Training-log statistics whose means go into a run's sidecar (with PPO's approx. KL)."""


@contextlib.contextmanager
def trained(
    make_env: EnvFactory,
    build: Callable[[VecEnv], BaseAlgorithm],
    *,
    seed: int,
    n_envs: int,
    normalize: dict[str, Any] | None,
    gamma: float,
    total_steps: int,
    settings: EvalSettings,
    progress: ProgressFn,
) -> Iterator[tuple[RunResult, BaseAlgorithm]]:
    """Trains a model with periodic evaluation; yields its result and the trained model.

    The result holds the evaluation table, the training log (SB3 logger values: ESA
    statistics, losses) as the extra table ``log``, and the mean of each ``esa/`` statistic
    in the sidecar. Everything (envs, ESA sessions) is closed when the block exits.

    Args:
        make_env: makes one env; the training envs are ``n_envs`` of them seeded from
            ``seed``, the evaluation env one more.
        build: the model on the training envs.
        seed: the run's seed.
        n_envs: training envs.
        normalize: ``VecNormalize`` keyword arguments, or None (see the module docstring).
        gamma: the discount of the normalized rewards.
        total_steps: environment steps of training.
        settings: the evaluation's interval and episodes.
        progress: receives the step count as training goes.
    """
    env: VecEnv = make_vec_env(make_env, n_envs=n_envs, seed=seed)
    eval_env: gym.Env[Any, Any] = make_env()
    if normalize is not None:
        stats = VecNormalize(env, gamma=gamma, **normalize)
        env, eval_env = stats, FrozenNormalization(eval_env, stats)
    model: BaseAlgorithm | None = None
    try:
        model = build(env)
        frame, log = train_and_evaluate(model, total_steps, eval_env, settings, seed, progress)
        means = {
            f"mean {key}": float(log[key].mean())
            for key in log.columns
            if key.startswith(LOGGED_MEANS) or key == "train/approx_kl"
        }
        yield RunResult(frame, means, {"log": log}), model
    finally:
        if model is not None and hasattr(model, "esa_close"):
            model.esa_close()
        env.close()
        eval_env.close()
