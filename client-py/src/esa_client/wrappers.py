"""``EsaActionWrapper``: ESA for any trainer, as a gymnasium wrapper around the environment."""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from typing import Any, SupportsFloat

import gymnasium as gym
import numpy as np

from .client import EsaClient
from .config import EsaConfig
from .env_dt import env_dt
from .errors import EsaError

QFunction = Callable[[Any, np.ndarray], SupportsFloat]
"""``q_fn(observation, action) -> float``: the learner's critic at one state-action pair."""


class EsaActionWrapper(gym.ActionWrapper, gym.utils.RecordConstructorArgs):
    """Improves every action the agent takes with ESA before the env sees it.

    For each ``step(action)``: the action is probed around, ``q_fn(obs, probe)``
    scores the probe at the current observation, and the improved action from the
    server is what the wrapped env executes. ``info["esa_action"]`` holds that
    applied action, so a learner can store it (the paper stores ``a_t + v``).
    Each ``reset`` starts a new ESA episode.

    Example::

        env = EsaActionWrapper(gym.make("Pendulum-v1"), q_fn=lambda o, a: critic(o, a))

    Args:
        env: A gymnasium env with a ``Box`` action space.
        q_fn: ``q_fn(observation, action) -> float``, evaluated once per step.
        esa_config: ESA hyperparameters (default ``EsaConfig()``); amplitudes are in
            the env's action units.
        client: The client to create the session on; None spawns a private server
            that is stopped by ``close()``.
    """

    def __init__(
        self,
        env: gym.Env,
        q_fn: QFunction,
        esa_config: EsaConfig | None = None,
        client: EsaClient | None = None,
    ) -> None:
        """Creates the ESA session for this env."""
        # Recorded so that gymnasium can re-create the wrapper from the env spec.
        gym.utils.RecordConstructorArgs.__init__(
            self, q_fn=q_fn, esa_config=esa_config, client=client
        )
        gym.ActionWrapper.__init__(self, env)
        space = env.action_space
        if not isinstance(space, gym.spaces.Box):
            raise ValueError(f"expected a Box action space, got {space}")
        esa = esa_config if esa_config is not None else EsaConfig()
        config = esa.session_config(
            int(np.prod(space.shape)),
            env_dt(env, esa.dt),
            space.low.reshape(-1),
            space.high.reshape(-1),
        )
        self._owns_client = client is None
        self._client = EsaClient.spawn() if client is None else client
        try:
            self._session = self._client.create_session(config)
        except BaseException:
            if self._owns_client:
                self._client.close()
            raise
        self._q_fn = q_fn
        self._obs: Any = None
        self._episode_start = True

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        """Resets the env; the next action starts a new ESA episode."""
        obs, info = self.env.reset(**kwargs)
        self._obs, self._episode_start = obs, True
        return obs, info

    def action(self, action: Any) -> np.ndarray:
        """Returns the ESA-improved version of ``action`` for the current observation."""
        space = self.action_space
        sampled = np.asarray(action, dtype=np.float64).reshape(-1)
        probe = self._session.probe(sampled, episode_start=self._episode_start)
        self._episode_start = False
        q_value = float(self._q_fn(self._obs, probe.reshape(space.shape).astype(space.dtype)))
        improved = self._session.report(q_value)
        return improved.reshape(space.shape).astype(space.dtype)

    def step(self, action: Any) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        """Steps the env with the improved action (also returned as ``info["esa_action"]``)."""
        applied = self.action(action)
        obs, reward, terminated, truncated, info = self.env.step(applied)
        self._obs = obs
        return obs, reward, terminated, truncated, {**info, "esa_action": applied}

    def close(self) -> None:
        """Closes the session (and the private server, if this wrapper spawned it) and the env."""
        with contextlib.suppress(EsaError):
            self._session.close()
        if self._owns_client:
            self._client.close()
        super().close()
