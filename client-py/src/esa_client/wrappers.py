"""``EsaActionWrapper``: ESA for any trainer, as a gymnasium wrapper around the environment."""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from typing import Any, SupportsFloat

import gymnasium as gym
import numpy as np

from .client import Where, resolve_client
from .config import EsaConfig
from .env_dt import env_dt
from .errors import EsaError

QFunction = Callable[[Any, np.ndarray], SupportsFloat]
"""``q_fn(observation, action) -> float``: the learner's critic at one state-action pair."""

ActionScale = float | np.ndarray | Callable[[Any], Any]
"""sigma: a scalar, one value per action dimension, or ``f(observation)`` giving either."""


class WrapperSessions:
    """What both wrappers hold: the ESA sessions of their envs, on a client they may own.

    Args:
        space: The (single) env's ``Box`` action space.
        n_envs: How many envs, one session each.
        dt: The envs' control period.
        esa: ESA hyperparameters (None: ``EsaConfig()``).
        client: Where the sessions live: a client (it stays the caller's), a string
            :meth:`EsaClient.open` parses (the wrapper closes that client), or None:
            ``EsaClient.in_process()``.

    Raises:
        ValueError: If ``space`` is not a ``Box`` or an ESA setting does not fit the env.
    """

    def __init__(
        self, space: gym.Space[Any], n_envs: int, dt: float, esa: EsaConfig | None, client: Where
    ) -> None:
        """Creates the sessions (closing the client it made if that fails)."""
        if not isinstance(space, gym.spaces.Box):
            raise ValueError(f"expected a Box action space, got {space}")
        esa = esa if esa is not None else EsaConfig()
        config = esa.session_config(
            int(np.prod(space.shape)), dt, space.low.reshape(-1), space.high.reshape(-1)
        )
        self.space: gym.spaces.Box = space
        self.paired = esa.paired_response
        self.client, self._owns_client = resolve_client(client)
        try:
            self.batch = self.client.create_batch(config, n_envs)
        except BaseException:
            if self._owns_client:
                self.client.close()
            raise

    def close(self) -> None:
        """Closes the sessions, and the client if it made it."""
        with contextlib.suppress(EsaError):
            self.batch.close()
        if self._owns_client:
            self.client.close()


class EsaActionWrapper(gym.ActionWrapper, gym.utils.RecordConstructorArgs):
    """Improves every action the agent takes with ESA before the env sees it.

    For each ``step(action)``, ``q_fn(obs, probe)`` scores the probe (and, with ``paired_response``,
    the applied action), and the env executes Algorithm 1's action ``a_t + v(t)``, also
    ``info["esa_action"]`` for the learner to store. Each ``reset`` starts a new ESA episode.

    Args:
        env: A gymnasium env with a ``Box`` action space.
        q_fn: ``q_fn(observation, action) -> float``, evaluated once per step.
        esa: ESA hyperparameters (default ``EsaConfig()``), in the env's action units.
        client: Where the session lives, as for :class:`WrapperSessions`.
        action_scale: sigma, the policy's standard deviation if the learner has one: a
            scalar, one value per action dimension, or ``f(observation)``; None = 1.
    """

    def __init__(
        self,
        env: gym.Env,
        q_fn: QFunction,
        *,
        esa: EsaConfig | None = None,
        client: Where = None,
        action_scale: ActionScale | None = None,
    ) -> None:
        """Creates the ESA session for this env."""
        gym.utils.RecordConstructorArgs.__init__(
            self, q_fn=q_fn, esa=esa, client=client, action_scale=action_scale
        )
        gym.ActionWrapper.__init__(self, env)
        dt = env_dt(env, None if esa is None else esa.dt)
        self._sessions = WrapperSessions(env.action_space, 1, dt, esa, client)
        self._batch = self._sessions.batch
        self._paired = self._sessions.paired
        self._q_fn, self._action_scale = q_fn, action_scale
        self._obs: Any = None
        self._episode_start = True

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        """Resets the env; the next action starts a new ESA episode."""
        obs, info = self.env.reset(**kwargs)
        self._obs, self._episode_start = obs, True
        return obs, info

    def action(self, action: Any) -> np.ndarray:
        """Returns the action to execute for ``action``: ``clip(a_t + v(t))`` (Algorithm 1)."""
        space = self.action_space
        sampled = np.asarray(action, dtype=np.float64).reshape(-1)
        scale = self._action_scale
        scale = scale(self._obs) if callable(scale) else scale

        def critic(points: np.ndarray) -> list[float]:
            # One row (the probe), or two with paired_response (the probe, then the applied).
            return [
                float(self._q_fn(self._obs, point.reshape(space.shape).astype(space.dtype)))
                for point in points
            ]

        _, applied = self._batch.step(
            sampled[None], critic, [self._episode_start], action_scales=scale, paired=self._paired
        )
        self._episode_start = False
        executed: np.ndarray = applied[0].reshape(space.shape).astype(space.dtype)
        return executed

    def step(self, action: Any) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        """Steps the env with the improved action (also returned as ``info["esa_action"]``)."""
        applied = self.action(action)
        obs, reward, terminated, truncated, info = self.env.step(applied)
        self._obs = obs
        return obs, reward, terminated, truncated, {**info, "esa_action": applied}

    def close(self) -> None:
        """Closes the session, the client if the wrapper made it, and the env."""
        self._sessions.close()
        super().close()
