"""What ESASAC and ESATD3 share: the probed twin critic, its gate, and the shifted action."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, cast

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.noise import ActionNoise

from ..common.action_frame import ActionFrame
from ..common.controls import (
    REPORT_EVERY,
    Acted,
    gradient_shift_size,
    gradient_size,
    unit_gradient,
)
from ..common.quadratic_head import rank_correlation
from ..config import EsaConfig
from ..transports.base import SMALLEST_SCALE
from .mixin import EsaMixin, tile_obs

if TYPE_CHECKING:
    from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm as _Algorithm
    from stable_baselines3.common.policies import ContinuousCritic
else:
    _Algorithm = object


class OffPolicyEsaMixin(EsaMixin, _Algorithm):
    """ESA on an SB3 off-policy actor-critic whose critic is a twin ``Q(s, a)``.

    Works in the squashed action space [-1, 1] (the replay buffer's). ESA probes the mean of
    the Polyak target twins (steadier than the online ones, which the actor chases).
    Subclasses say where the policy's action is and how wide it is
    (:meth:`_policy_mean_and_std`). From fade strength ``f = 0`` on the env executes
    ``a_t`` and no session steps.
    """

    critic: ContinuousCritic
    critic_target: ContinuousCritic
    gate_every = 1000
    """Env steps between two checks of the gate."""

    def __init__(self, policy: Any, env: Any, *args: Any, **kwargs: Any) -> None:
        """Creates the model; the ESA sessions are created when training starts."""
        self._esa_active = False
        self._esa_gate_checked_at = 0
        self._esa_shifted_steps = 0
        super().__init__(policy, env, *args, **kwargs)

    @staticmethod
    def _default_esa() -> EsaConfig:
        return EsaConfig.off_policy()

    def _policy_mean_and_std(self, obs: Any) -> tuple[th.Tensor, th.Tensor]:
        """The policy's action and its spread sigma in [-1, 1] units, each ``(batch, D)``."""
        raise NotImplementedError

    def _policy_sample(self, obs: Any) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        """One actor call's sample as SB3's ``_predict`` draws it, and the mean and sigma."""
        raise NotImplementedError

    def _make_esa_frame(self, box: spaces.Box) -> ActionFrame:
        return ActionFrame.squashed(box)

    def _probe_q(self, obs: Any, actions: th.Tensor) -> th.Tensor:
        """The probed critic at ``(obs, actions)``: the target twins' mean, ``(batch,)``."""
        return th.cat(self.critic_target(obs, actions), dim=1).mean(dim=1)

    def _esa_q(self, obs: Any) -> Any:
        def q_fn(actions: np.ndarray) -> np.ndarray:
            reps = len(actions) // self.n_envs
            with th.no_grad():
                action_tensor = th.as_tensor(actions, dtype=th.float32, device=self.device)
                return self._probe_q(tile_obs(obs, reps), action_tensor).cpu().numpy()

        return q_fn

    def _sample_action(
        self,
        learning_starts: int,
        action_noise: ActionNoise | None = None,
        n_envs: int = 1,
    ) -> tuple[np.ndarray, np.ndarray]:
        self._update_gate(learning_starts)
        if not self._esa_active:
            return super()._sample_action(learning_starts, action_noise, n_envs)
        assert self._last_obs is not None  # in rollouts
        obs, _ = self.policy.obs_to_tensor(self._last_obs)
        buffer_action, mean, std = self._sampled(obs, action_noise)
        strength = self._esa_strength()
        report = strength > 0 and self._esa_shifted_steps % REPORT_EVERY == 0
        mu = mean.reshape(n_envs, -1).cpu().numpy().astype(np.float64)
        sigma = np.maximum(std.reshape(n_envs, -1).cpu().numpy(), SMALLEST_SCALE)
        sampled = buffer_action.reshape(n_envs, -1)
        executed, shift = self._shifted(obs, sampled, mu, sigma, strength)
        if strength > 0:
            self._esa_shifted_steps += 1
        if report:
            frame = self.esa_frame
            self._report_shift(strength, (sampled, shift, mu, sigma, frame.low, frame.high))
        buffer_action = executed.reshape(buffer_action.shape).astype(buffer_action.dtype)
        return self.policy.unscale_action(buffer_action), buffer_action

    def _sampled(
        self, obs: Any, action_noise: ActionNoise | None
    ) -> tuple[np.ndarray, th.Tensor, th.Tensor]:
        """SB3's exploratory action in [-1, 1] (its buffer action), the mean and sigma.

        ``OffPolicyAlgorithm._sample_action`` after the warm-up, with one actor call for all
        three; the sample is unscaled and rescaled as SB3's, so that its bits are SB3's.
        """
        with th.no_grad():
            actions, mean, std = self._policy_sample(obs)
        sample = actions.cpu().numpy().reshape((-1, *(self.action_space.shape or ())))
        scaled: np.ndarray = self.policy.scale_action(self.policy.unscale_action(sample))
        if action_noise is not None:
            scaled = np.clip(scaled + action_noise(), -1, 1)
        return scaled, mean, std

    def _shifted(
        self, obs: Any, sampled: np.ndarray, mu: np.ndarray, sigma: np.ndarray, strength: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """The env's actions and the shift on ``sampled`` (``a_t``, with TD3's noise), (N, D)."""

        def execute(shift: np.ndarray) -> np.ndarray:
            executed: np.ndarray = np.clip(sampled + shift, -1.0, 1.0)
            return executed

        def session() -> Acted:
            # The session's own action, not a_t + (applied - a_t): the same bits.
            applied = self._esa_step(obs, sampled, sigma, strength)
            return applied, applied - sampled

        return self._control_shift().act(
            session,
            lambda: self._gradient_shift(obs, sampled, sigma, strength),
            execute,
            self._episode_starts(),
        )

    def _episode_starts(self) -> np.ndarray:
        """True where an env starts an episode at this step."""
        assert self._last_episode_starts is not None  # set by _setup_learn and each step
        return self._last_episode_starts

    def _esa_step(
        self, obs: Any, anchor: np.ndarray, sigma: np.ndarray, strength: float
    ) -> np.ndarray:
        """Algorithm 1's step of every env's session at ``anchor``: the applied actions."""
        return self._esa_runtime().step(
            anchor, self._episode_starts(), self._esa_q(obs), sigma, strength=strength
        )

    def _gradient_shift(
        self, obs: Any, anchor: np.ndarray, sigma: np.ndarray, strength: float = 1.0
    ) -> np.ndarray:
        """``f kappa sigma u``: the gradient control's shift, ``u`` the unit gradient at ``anchor``.

        At strength ``f`` 0 no gradient is computed.
        """
        if strength <= 0:
            return np.zeros(anchor.shape)
        scale = gradient_size(strength, self.esa.trust_region)
        actions = th.as_tensor(anchor, dtype=th.float32, device=self.device).requires_grad_(True)
        # autograd.grad, not backward: the critics' own .grad must not collect this.
        (grad,) = th.autograd.grad(self._probe_q(obs, actions).sum(), actions)
        unit = unit_gradient(grad.cpu().numpy().astype(np.float64) * sigma)
        self.logger.record_mean("esa/shift_over_std", gradient_shift_size(scale, unit))
        shift: np.ndarray = scale * sigma * unit
        return shift

    def _update_gate(self, learning_starts: int) -> None:
        warming_up = self.num_timesteps < learning_starts and not (
            self.use_sde and self.use_sde_at_warmup
        )
        if warming_up:
            return
        if self.esa.gate is None:
            self._esa_active = True
            return
        if self.num_timesteps - self._esa_gate_checked_at < self.gate_every:
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
        # Off-policy SB3 does not track episode starts; ESA's sessions need them.
        self._last_episode_starts = np.asarray(dones, dtype=bool).copy()
