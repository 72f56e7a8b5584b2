"""``ESASAC``: stable-baselines3 SAC whose exploratory actions are shifted by ESA."""

from __future__ import annotations

from typing import Any, Literal, cast

import numpy as np
import torch as th
from stable_baselines3 import SAC
from stable_baselines3.common.noise import ActionNoise

from ..common.advantage_head import rank_correlation
from .mixin import EsaMixin, tile_obs

ProbeCritic = Literal["online_min", "online_mean", "target_min", "target_mean"]
PROBE_CRITICS: tuple[str, ...] = ("online_min", "online_mean", "target_min", "target_mean")


class ESASAC(EsaMixin, SAC):
    """SAC with Extremum-Seeking Action selection; a drop-in for ``stable_baselines3.SAC``.

    Each step, for every env of the VecEnv (one ESA session each), the action SAC
    samples is probed with a sinusoidal perturbation, a critic scores the probes and the
    env executes ``a_t + v(t)`` (Algorithm 1), which is also what the replay buffer
    stores. ESA works in SAC's squashed action space: probes, shifts and amplitudes are
    in [-1, 1] units, and the action scale is the policy's local standard deviation
    there, ``min((1 - tanh(mu)^2) std, 1)``.

    ESA waits until the critic has learned something about actions (``EsaConfig.gate``):
    every ``esa_gate_every`` steps after ``learning_starts`` it computes, on the
    transitions collected since the last check, the rank correlation between the
    critic's ``Q(s, a) - Q(s, mu)`` and the one-step advantage ``r + gamma V(s') - V(s)``
    with ``V(s) = Q(s, mu)``. With ``gate=None`` ESA starts at ``learning_starts``.

    With ``EsaConfig(learning_rate=0)`` the shift stays 0 and training equals plain SAC
    step for step (the gate and the probes draw no random numbers).
    ``predict`` is unchanged: evaluation uses the plain policy.

    Example::

        model = ESASAC("MlpPolicy", "Pendulum-v1")
        model.learn(10_000)

    Args:
        policy: As for SAC.
        env: As for SAC.
        esa: The ESA hyperparameters (default ``EsaConfig()``).
        esa_address: An esa-server address (``host:port`` or ``unix:/path``); None
            spawns a private server that stops with the model (or ``esa_close()``)
            when ``esa_engine`` is ``"sidecar"``.
        esa_engine: ``"inprocess"`` (esa-core in this process) or ``"sidecar"`` (an
            esa-server); None: ``esa_address``'s server when given, else in-process.
        esa_probe_critic: Which critic ESA probes: the online or the Polyak target
            networks, the minimum or the mean of the twins.
        esa_gate_every: Env steps between two checks of the gate.
        **kwargs: Any other SAC argument.

    Raises:
        ValueError: If the action space is not a Box, ``esa_probe_critic`` is unknown, or an
            ESA setting is invalid for this env.
    """

    def __init__(
        self,
        policy: Any,
        env: Any,
        *args: Any,
        esa_probe_critic: ProbeCritic = "target_mean",
        esa_gate_every: int = 1000,
        **kwargs: Any,
    ) -> None:
        """Creates the SAC model; the ESA sessions are created when training starts."""
        if esa_probe_critic not in PROBE_CRITICS:
            raise ValueError(
                f"expected esa_probe_critic in {PROBE_CRITICS}, got {esa_probe_critic!r}"
            )
        if not (isinstance(esa_gate_every, int) and esa_gate_every >= 1):
            raise ValueError(f"expected esa_gate_every >= 1, got {esa_gate_every!r}")
        self.esa_probe_critic = esa_probe_critic
        self.esa_gate_every = esa_gate_every
        self._esa_active = False
        self._esa_gate_checked_at = 0
        super().__init__(policy, env, *args, **kwargs)

    def _esa_space(self) -> tuple[np.ndarray, np.ndarray]:
        dim = int(np.prod(self.action_space.shape or ()))
        return -np.ones(dim), np.ones(dim)

    def _esa_env_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self._esa_space()

    def _probe_q(self, obs: Any, actions: th.Tensor) -> th.Tensor:
        """The probed critic at ``(obs, actions)``, shape ``(batch,)``."""
        online, reduce = self.esa_probe_critic.split("_")
        critic = self.critic if online == "online" else self.critic_target
        q = th.cat(critic(obs, actions), dim=1)
        return q.min(dim=1).values if reduce == "min" else q.mean(dim=1)

    def _esa_q(self, obs: Any) -> Any:
        def q_fn(actions: np.ndarray) -> np.ndarray:
            reps = len(actions) // self.n_envs
            with th.no_grad():
                action_tensor = th.as_tensor(actions, dtype=th.float32, device=self.device)
                return self._probe_q(tile_obs(obs, reps), action_tensor).cpu().numpy()

        return q_fn

    def _policy_mean_and_std(self, obs: Any) -> tuple[th.Tensor, th.Tensor]:
        """The squashed policy's mean action and its standard deviation in [-1, 1] units.

        The std is tanh's linearization at the mean, ``(1 - tanh(mu)^2) std``, capped at 1:
        no distribution on [-1, 1] spreads wider than that.
        """
        with th.no_grad():
            mean, log_std, _ = self.actor.get_action_dist_params(obs)
            squashed = th.tanh(mean)
            return squashed, ((1.0 - squashed**2) * log_std.exp()).clamp(max=1.0)

    def _sample_action(
        self,
        learning_starts: int,
        action_noise: ActionNoise | None = None,
        n_envs: int = 1,
    ) -> tuple[np.ndarray, np.ndarray]:
        action, buffer_action = super()._sample_action(learning_starts, action_noise, n_envs)
        self._update_gate(learning_starts)
        if not self._esa_active:
            return action, buffer_action
        assert self._last_obs is not None and self._last_episode_starts is not None  # in rollouts
        obs, _ = self.policy.obs_to_tensor(self._last_obs)
        _, std = self._policy_mean_and_std(obs)
        applied = self._esa_runtime().step(
            buffer_action.reshape(n_envs, -1),
            self._last_episode_starts,
            self._esa_q(obs),
            std.reshape(n_envs, -1).cpu().numpy(),
        )
        buffer_action = applied.reshape(buffer_action.shape).astype(buffer_action.dtype)
        return self.policy.unscale_action(buffer_action), buffer_action

    def _update_gate(self, learning_starts: int) -> None:
        warming_up = self.num_timesteps < learning_starts and not (
            self.use_sde and self.use_sde_at_warmup
        )
        if warming_up:
            return
        if self.esa.gate is None:
            self._esa_active = True
            return
        if self.num_timesteps - self._esa_gate_checked_at < self.esa_gate_every:
            return
        assert self.replay_buffer is not None  # set up with the model
        recent = min(self.num_timesteps - self._esa_gate_checked_at, self.replay_buffer.size())
        self._esa_gate_checked_at = self.num_timesteps
        quality = self._critic_quality(recent // self.n_envs)
        self._esa_active = quality >= self.esa.gate
        self.logger.record("esa/gate_correlation", quality)
        self.logger.record("esa/active", float(self._esa_active))

    def _critic_quality(self, steps: int) -> float:
        """Rank correlation of ``Q(s, a) - Q(s, mu)`` with ``r + gamma V(s') - V(s)``.

        Over the last ``steps`` transitions of every env, read from the replay buffer
        directly (its sampler would draw from numpy's global generator).
        """
        rb = self.replay_buffer
        assert rb is not None  # set up with the model
        idx = (rb.pos - 1 - np.arange(max(steps, 2))) % rb.buffer_size

        def flat(array: np.ndarray) -> np.ndarray:
            values: np.ndarray = array[idx].reshape(len(idx) * self.n_envs, *array.shape[2:])
            return values

        def normalized_obs(array: np.ndarray) -> np.ndarray:
            # A ReplayBuffer holds array observations (dict ones live in a DictReplayBuffer).
            return cast(np.ndarray, rb._normalize_obs(flat(array), self._vec_normalize_env))

        next_obs = rb.next_observations if not rb.optimize_memory_usage else None
        if next_obs is None:
            return 0.0
        obs = rb.to_torch(normalized_obs(rb.observations))
        nxt = rb.to_torch(normalized_obs(next_obs))
        actions = rb.to_torch(flat(rb.actions))
        rewards = rb._normalize_reward(flat(rb.rewards), self._vec_normalize_env)
        alive = 1.0 - flat(rb.dones) * (1.0 - flat(rb.timeouts))
        with th.no_grad():
            mu, _ = self._policy_mean_and_std(obs)
            mu_next, _ = self._policy_mean_and_std(nxt)
            value = self._probe_q(obs, mu).cpu().numpy()
            value_next = self._probe_q(nxt, mu_next).cpu().numpy()
            predicted = self._probe_q(obs, actions).cpu().numpy() - value
        advantage = rewards + self.gamma * alive * value_next - value
        return rank_correlation(predicted, advantage)

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
