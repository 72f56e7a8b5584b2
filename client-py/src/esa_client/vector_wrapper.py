"""``EsaVectorWrapper``: ESA for a gymnasium vector env, one batched critic call per step."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
import numpy.typing as npt

from .client import Where
from .config import EsaConfig
from .env_dt import env_dt
from .wrappers import WrapperSessions

BatchQFunction = Callable[[Any, np.ndarray], npt.ArrayLike]
"""``q_fn(obs_batch, actions_batch) -> (M,)``: the critic at M state-action pairs at once.

``obs_batch`` is the batched observation (twice, stacked, when the response is paired).
"""

BatchActionScale = float | np.ndarray | Callable[[Any], npt.ArrayLike]
"""sigma: a scalar, one value per action dimension, one row per env, or ``f(obs_batch)``."""


def _stack_obs(obs: Any) -> Any:
    """The batched observation twice along axis 0 (dicts and tuples item by item)."""
    if isinstance(obs, dict):
        return {key: _stack_obs(value) for key, value in obs.items()}
    if isinstance(obs, tuple):
        return tuple(_stack_obs(value) for value in obs)
    array = np.asarray(obs)
    return np.concatenate([array, array], axis=0)


class EsaVectorWrapper(gym.vector.VectorWrapper):
    """Improves the actions of all N envs of a vector env with ESA, one critic call per step.

    ``q_fn`` scores the N probes (and, with ``paired_response``, the N applied actions too); the
    envs execute Algorithm 1's actions ``a_t + v(t)``, also ``info["esa_action"]`` for the learner
    to store. An env that ends starts a new ESA episode with its next real action (under
    ``NEXT_STEP`` autoreset, the step after the reset step, whose action the env ignores).

    Args:
        env: A vector env with a ``Box`` single action space.
        q_fn: ``q_fn(obs_batch, actions_batch) -> (M,)``, called once per step.
        esa: ESA hyperparameters (default ``EsaConfig()``).
        client: Where the sessions live, as for :class:`~esa_client.wrappers.WrapperSessions`.
        action_scale: sigma, the policy's standard deviation if the learner has one: a
            scalar, one value per action dimension, ``(N, D)``, or ``f(obs_batch)``.
        dt: The envs' control period; None = ``esa.dt``, else the first sub-env's.
    """

    def __init__(
        self,
        env: gym.vector.VectorEnv,
        q_fn: BatchQFunction,
        *,
        esa: EsaConfig | None = None,
        client: Where = None,
        action_scale: BatchActionScale | None = None,
        dt: float | None = None,
    ) -> None:
        """Creates one ESA session per env."""
        super().__init__(env)
        space = env.single_action_space
        override = dt if dt is not None else None if esa is None else esa.dt
        self._sessions = WrapperSessions(space, env.num_envs, env_dt(env, override), esa, client)
        self._space = self._sessions.space
        self._q_fn = q_fn
        self.action_scale = action_scale
        """sigma for the next steps; trainers whose policy std changes set it before ``step``."""
        mode = env.metadata.get("autoreset_mode")
        self._next_step = mode in (None, gym.vector.AutoresetMode.NEXT_STEP)
        self._obs: Any = None
        self._starts = np.ones(env.num_envs, dtype=bool)
        self._resetting = np.zeros(env.num_envs, dtype=bool)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        """Resets the envs; every env's next action starts a new ESA episode."""
        obs, info = self.env.reset(seed=seed, options=options)
        self._obs = obs
        self._starts[:] = True
        self._resetting[:] = False
        return obs, info

    def improve(self, actions: Any) -> np.ndarray:
        """Returns the actions to execute, ``clip(a_t + v(t))`` of each env, shape ``(N, ...)``."""
        if self._obs is None:
            raise RuntimeError("call reset() before step()")
        n, shape = self.num_envs, self._space.shape
        sampled = np.asarray(actions, dtype=np.float64).reshape(n, -1)
        scale = self.action_scale
        scales = scale(self._obs) if callable(scale) else scale
        scales = None if scales is None else np.asarray(scales)
        obs = _stack_obs(self._obs) if self._sessions.paired else self._obs

        def critic(points: np.ndarray) -> np.ndarray:
            q = self._q_fn(obs, points.reshape(-1, *shape).astype(self._space.dtype))
            return np.asarray(q, dtype=np.float64).reshape(-1)

        _, applied = self._sessions.batch.step(
            sampled, critic, self._starts, action_scales=scales, paired=self._sessions.paired
        )
        return applied.reshape(n, *shape).astype(self._space.dtype)

    def step(self, actions: Any) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Steps the envs with the improved actions (also ``info["esa_action"]``)."""
        applied = self.improve(actions)
        obs, rewards, terminations, truncations, info = self.env.step(applied)
        done = np.logical_or(terminations, truncations)
        # NEXT_STEP: this step's action was ignored by an env that reset now; its first real
        # action comes next, so a new ESA episode starts there again.
        self._starts = done | self._resetting if self._next_step else done.copy()
        self._resetting = done if self._next_step else np.zeros_like(done)
        self._obs = obs
        return obs, rewards, terminations, truncations, {**info, "esa_action": applied}

    def close(self, **kwargs: Any) -> None:
        """Closes the sessions (and the client, if this wrapper made it) and the envs."""
        self._sessions.close()
        super().close(**kwargs)
