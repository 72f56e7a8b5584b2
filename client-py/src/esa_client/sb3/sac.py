"""``ESASAC``: stable-baselines3 SAC whose exploratory actions are improved by ESA."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch as th
from stable_baselines3 import SAC
from stable_baselines3.common.noise import ActionNoise

from .mixin import EsaMixin, tile_obs


class ESASAC(EsaMixin, SAC):
    """SAC with Extremum-Seeking Action selection; a drop-in for ``stable_baselines3.SAC``.

    Each step, for every env of the VecEnv (one ESA session each), the action SAC
    samples is probed with a sinusoidal perturbation, the critic scores the probe
    and the ESA server returns the improved action, which is applied to the env
    and stored in the replay buffer (paper, Algorithm 1).

    ESA works in SAC's squashed action space: probes, shifts and ``EsaConfig``
    amplitudes are in [-1, 1] units, and the probe's value is the minimum over the
    critic's Q-networks (the same pessimistic estimate SAC's actor maximizes).
    During the random warm-up (``learning_starts``) the critic is untrained, so ESA
    stays out of it. ``predict`` is unchanged: evaluation uses the plain policy.

    Example::

        model = ESASAC("MlpPolicy", "Pendulum-v1", esa=EsaConfig(amplitude=0.2))
        model.learn(10_000)

    Args:
        policy: As for SAC.
        env: As for SAC.
        esa: The ESA hyperparameters (default ``EsaConfig()``).
        esa_address: An esa-server address (``host:port`` or ``unix:/path``); None
            spawns a private server that stops with the model (or ``esa_close()``).
        **kwargs: Any other SAC argument.
    """

    def _esa_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        dim = int(np.prod(self.action_space.shape))
        return -np.ones(dim), np.ones(dim)

    def _esa_q(self, actions: np.ndarray) -> np.ndarray:
        obs, _ = self.policy.obs_to_tensor(self._last_obs)
        reps = len(actions) // self.n_envs
        with th.no_grad():
            action_tensor = th.as_tensor(actions, dtype=th.float32, device=self.device)
            q_values = th.cat(self.critic(tile_obs(obs, reps), action_tensor), dim=1)
            return q_values.min(dim=1).values.cpu().numpy()

    def _sample_action(
        self,
        learning_starts: int,
        action_noise: ActionNoise | None = None,
        n_envs: int = 1,
    ) -> tuple[np.ndarray, np.ndarray]:
        action, buffer_action = super()._sample_action(learning_starts, action_noise, n_envs)
        if self.num_timesteps < learning_starts and not (self.use_sde and self.use_sde_at_warmup):
            return action, buffer_action
        sampled = buffer_action.reshape(n_envs, -1)
        improved = self._esa_runtime().improve(sampled, self._last_episode_starts, self._esa_q)
        buffer_action = improved.reshape(buffer_action.shape).astype(buffer_action.dtype)
        return self.policy.unscale_action(buffer_action), buffer_action

    def _store_transition(
        self,
        replay_buffer: Any,
        buffer_action: np.ndarray,
        new_obs: Any,
        reward: np.ndarray,
        dones: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        super()._store_transition(replay_buffer, buffer_action, new_obs, reward, dones, infos)
        # Off-policy SB3 does not track episode starts; ESA needs them to reset the sessions.
        self._last_episode_starts = np.asarray(dones, dtype=bool).copy()
