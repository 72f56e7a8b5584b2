"""``ESAPPO``: stable-baselines3 PPO whose sampled actions are shifted by ESA."""

from __future__ import annotations

import functools
from typing import cast

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.distributions import Distribution
from stable_baselines3.common.preprocessing import preprocess_obs
from stable_baselines3.common.utils import obs_as_tensor
from stable_baselines3.common.vec_env import VecEnv
from torch import nn

from ..common.action_frame import ActionFrame
from ..common.controls import (
    REPORT_EVERY,
    Acted,
    gradient_shift_size,
    gradient_size,
    unit_gradient,
)
from ..common.head_step import head_critic, head_shift, shifted
from ..common.quadratic_head import (
    CriticAtStep,
    QuadraticHead,
    Rollout,
    critic_quality,
    fit_critic,
    normalized,
)
from ..config import EsaConfig
from .decoupled_ppo import DecoupledPPO
from .mixin import EsaMixin


class ESAPPO(EsaMixin, DecoupledPPO):
    """PPO with Extremum-Seeking Action selection; a drop-in for ``stable_baselines3.PPO``.

    ESA probes a head quadratic in the action (:mod:`esa_client.common.quadratic_head`,
    fitted on the GAE advantages of the last ``head_rollouts`` rollouts); the rollout stores
    the executed ``a_t + v(t)``, unclipped, and the update is :class:`DecoupledPPO`'s (the
    SB3 guide says what each step does). ``squash_output`` policies and Dict observations
    are refused; ``predict`` is PPO's.

    Args:
        *args: PPO's positional arguments (``policy``, ``env``, ...).
        **kwargs: The ``esa_*`` arguments of :class:`~esa_client.sb3.mixin.EsaMixin`, and
            any other PPO argument.

    Raises:
        ValueError: If the action space is not a Box, the observations are a Dict, the policy
            squashes its output, or an ESA setting is invalid for this env.
    """

    head_hidden = 64
    """Hidden units of each of the head's two layers."""
    head_learning_rate = 1e-3
    """Adam learning rate of the head."""
    head_epochs = 5
    """Passes over its data each time the head is fitted."""
    head_batch_size = 256
    """Minibatch size of the head's fit."""
    head_rollouts = 4
    """How many of the latest rollouts the head is fitted on."""

    esa_head: nn.Module
    _esa_head_fitted = False
    _esa_active = False
    _esa_steps = 0

    @staticmethod
    def _default_esa() -> EsaConfig:
        return EsaConfig.ppo()

    def _setup_model(self) -> None:
        super()._setup_model()
        if self.policy.squash_output:
            raise ValueError(
                "expected a policy without squash_output for ESAPPO (the shifted sample "
                "must have a density under the policy), got squash_output=True"
            )
        features_dim = spaces.flatdim(self.observation_space)
        action_dim = int(np.prod(self.action_space.shape or ()))
        with th.random.fork_rng(devices=[]):  # building it must not move PPO's random stream
            self.esa_head = self._make_critic(features_dim, action_dim)
        self.esa_head.to(self.device)
        fused = self.device.type in ("cpu", "cuda") or None
        self.esa_head_optimizer = th.optim.Adam(
            self.esa_head.parameters(), lr=self.head_learning_rate, fused=fused
        )
        self._esa_rng = np.random.default_rng(self.seed)
        self._esa_head_data: list[Rollout] = []

    def _make_critic(self, features_dim: int, action_dim: int) -> nn.Module:
        """The critic ESA probes, a module of ``(features, z)``."""
        return QuadraticHead(features_dim, action_dim, self.head_hidden)

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts, variables = super()._get_torch_save_params()
        return [*state_dicts, "esa_head", "esa_head_optimizer"], variables

    def _excluded_save_params(self) -> list[str]:  # the next rollouts bring new data
        return [*super()._excluded_save_params(), "_esa_head_data"]

    def _make_esa_frame(self, box: spaces.Box) -> ActionFrame:
        return ActionFrame.scaled(box)

    def _head_features(self, obs: th.Tensor) -> th.Tensor:
        """The observation as the critic sees it: preprocessed as SB3 does, flattened."""
        pre = preprocess_obs(obs, self.observation_space, self.policy.normalize_images)
        assert isinstance(pre, th.Tensor)  # Dict observations are refused in _setup_model
        return pre.flatten(1).float()

    def _esa_policy_step(self, obs: th.Tensor) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        """SB3's ``policy(obs)`` with ESA: ``(a_t + v(t), values, log pi(a_t))``."""
        actions, values, log_prob = self.policy(obs)
        strength = self._esa_strength() if self._esa_active else 0.0
        if strength > 0.0:
            gaussian = _gaussian(self.policy.action_dist)
            sample = actions.reshape(len(actions), -1).cpu().numpy()
            mean, std = gaussian.mean.cpu().numpy(), gaussian.stddev.cpu().numpy()
            executed = self._esa_act(obs, sample, mean, std, strength)
            actions = th.from_numpy(executed).to(actions.device).reshape(actions.shape)
        return actions, values, log_prob

    def _esa_act(
        self, obs: th.Tensor, sample: np.ndarray, mean: np.ndarray, std: np.ndarray, f: float
    ) -> np.ndarray:
        """The env's actions ``a_t + v(t)``, float32 ``(N, D)``, at ESA's strength ``f``."""
        starts = self._last_episode_starts
        assert starts is not None  # set by SB3 before its rollouts

        execute = functools.partial(shifted, sample)

        def session() -> Acted:
            shift = self._session_shift(obs, sample, mean, std, starts, f)
            return execute(shift), shift

        executed, shift = self._control_shift().act(
            session, lambda: self._gradient_shift(obs, sample, mean, std, f), execute, starts
        )
        if self._esa_steps % REPORT_EVERY == 0:
            box = self.esa_frame.box
            low, high = box.low.reshape(-1), box.high.reshape(-1)
            self._report_shift(f, (sample, shift, mean, std, low, high))
        self._esa_steps += 1
        return executed

    def _critic_at_step(self, obs: th.Tensor, mean: np.ndarray, std: np.ndarray) -> CriticAtStep:
        """The critic at this step's states over actions in ESA units."""
        return head_critic(self.esa_head, self._head_features(obs), self.esa_frame, mean, std)

    def _session_shift(
        self,
        obs: th.Tensor,
        sample: np.ndarray,
        mean: np.ndarray,
        std: np.ndarray,
        starts: np.ndarray,
        f: float,
    ) -> np.ndarray:
        """ESA's shift ``v(t)`` in the Box's units, float64 ``(N, D)``: the sessions step."""
        critic = self._critic_at_step(obs, mean, std)
        return head_shift(
            self._esa_runtime(), critic.closed_form(), critic.std, self.esa_frame, sample, starts, f
        )

    def _gradient_shift(
        self, obs: th.Tensor, sample: np.ndarray, mean: np.ndarray, std: np.ndarray, f: float
    ) -> np.ndarray:
        """The gradient control's shift ``f kappa sigma u`` in the Box's units, ``(N, D)``."""
        critic = self._critic_at_step(obs, mean, std)
        frame = self.esa_frame
        size = gradient_size(f, self.esa.trust_region)
        unit = unit_gradient(critic.gradient((sample - frame.center) / frame.half_width))
        self.logger.record_mean("esa/shift_over_std", gradient_shift_size(size, unit))
        shift: np.ndarray = size * unit * std
        return shift

    def collect_rollouts(
        self,
        env: VecEnv,
        callback: BaseCallback,
        rollout_buffer: RolloutBuffer,
        n_rollout_steps: int,
    ) -> bool:
        """SB3's ``OnPolicyAlgorithm.collect_rollouts`` with ESA's step in the policy's place."""
        assert self._last_obs is not None, "No previous observation was provided"
        self.policy.set_training_mode(False)
        n_steps = 0
        rollout_buffer.reset()
        if self.use_sde:
            self.policy.reset_noise(env.num_envs)
        callback.on_rollout_start()
        while n_steps < n_rollout_steps:
            if self.use_sde and self.sde_sample_freq > 0 and n_steps % self.sde_sample_freq == 0:
                self.policy.reset_noise(env.num_envs)
            # inference_mode, not no_grad: no version counters or view records, a few
            # microseconds of every op; nothing of a step is differentiated later.
            with th.inference_mode():
                obs_tensor = obs_as_tensor(self._last_obs, self.device)  # type: ignore[arg-type]
                actions_t, values, log_probs = self._esa_policy_step(obs_tensor)  # type: ignore[arg-type]
            actions = actions_t.cpu().numpy()
            box = self.esa_frame.box
            clipped_actions = np.clip(actions, box.low, box.high)
            new_obs, rewards, dones, infos = env.step(clipped_actions)
            self.num_timesteps += env.num_envs
            callback.update_locals(locals())
            if not callback.on_step():
                return False
            self._update_info_buffer(infos, dones)
            n_steps += 1
            for idx, done in enumerate(dones):
                if (
                    done
                    and infos[idx].get("terminal_observation") is not None
                    and infos[idx].get("TimeLimit.truncated", False)
                ):
                    terminal_obs = self.policy.obs_to_tensor(infos[idx]["terminal_observation"])[0]
                    with th.inference_mode():
                        terminal_value = self.policy.predict_values(terminal_obs)[0]
                    rewards[idx] += self.gamma * terminal_value
            rollout_buffer.add(
                self._last_obs,  # type: ignore[arg-type]
                actions,
                rewards,
                self._last_episode_starts,  # type: ignore[arg-type]
                values,
                log_probs,
            )
            self._last_obs = new_obs  # type: ignore[assignment]
            self._last_episode_starts = dones
        with th.inference_mode():
            values = self.policy.predict_values(obs_as_tensor(new_obs, self.device))  # type: ignore[arg-type]
        rollout_buffer.compute_returns_and_advantage(last_values=values, dones=dones)
        callback.update_locals(locals())
        callback.on_rollout_end()
        return True

    def train(self) -> None:
        """The gate on the new rollout, PPO's update, then the critic's fit (on its own generator).

        Once the fade is over nothing probes the critic again: it is neither scored nor fitted.
        """
        probed_again = self._esa_strength() > 0.0
        if probed_again:
            self._check_gate()
        super().train()
        if probed_again:
            self.logger.record("esa/head_loss", self._fit_critic())

    def _fit_critic(self) -> float:
        """Fits the critic on the kept rollouts; returns the mean loss."""
        return fit_critic(
            self.esa_head,
            self.esa_head_optimizer,
            rollouts=self._esa_head_data,
            rng=self._esa_rng,  # the critic's own generator: PPO's stream stays as it is
            epochs=self.head_epochs,
            batch_size=self.head_batch_size,
        )

    def _check_gate(self) -> None:
        """Scores the critic on the new rollout (unseen; pi not yet updated), then keeps it."""
        buffer = self.rollout_buffer
        obs = buffer.to_torch(buffer.observations.reshape(-1, *buffer.obs_shape))
        actions = buffer.to_torch(buffer.actions.reshape(-1, buffer.action_dim))
        advantages = buffer.to_torch(buffer.advantages.reshape(-1))
        with th.no_grad():
            distribution = _gaussian(self.policy.get_distribution(obs))
            mean = distribution.mean.reshape(len(obs), -1)
            std = distribution.stddev.reshape(len(obs), -1)
        rollout = Rollout(self._head_features(obs), (actions - mean) / std, normalized(advantages))
        gate = self.esa.gate
        if self._esa_head_fitted:
            quality = critic_quality(self.esa_head, rollout, advantages)
            self.logger.record("esa/gate_correlation", quality)
            self._esa_active = gate is None or quality >= gate
        elif gate is None:
            self._esa_active = True
        self._esa_head_data = [*self._esa_head_data, rollout][-self.head_rollouts :]
        self._esa_head_fitted = True
        self.logger.record("esa/active", float(self._esa_active))


def _gaussian(distribution: Distribution) -> th.distributions.Normal:
    """The torch Normal under a non-squashing Box policy's DiagGaussian or gSDE distribution."""
    return cast(th.distributions.Normal, distribution.distribution)
