"""``ESAPPO``: stable-baselines3 PPO whose sampled actions are shifted by ESA."""

from __future__ import annotations

from typing import Any, cast

import numpy as np
import torch as th
import torch.nn.functional as F
from gymnasium import spaces
from stable_baselines3 import PPO
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.distributions import Distribution
from stable_baselines3.common.preprocessing import preprocess_obs
from stable_baselines3.common.utils import explained_variance, obs_as_tensor
from stable_baselines3.common.vec_env import VecEnv
from torch import nn

from ..common.controls import gradient_size, shift_report, unit_gradient
from ..common.quadratic_head import (
    CriticAtStep,
    QuadraticHead,
    Rollout,
    critic_quality,
    fit_critic,
    normalized,
)
from ..config import EsaConfig
from ..transports.base import SMALLEST_SCALE
from .esa_buffer import EsaRolloutBuffer, EsaRolloutBufferSamples
from .mixin import EsaMixin

REPORT_EVERY = 8
"""One step in this many records what the shifts did (:func:`shift_report`)."""


class ESAPPO(EsaMixin, PPO):
    """PPO with Extremum-Seeking Action selection; a drop-in for ``stable_baselines3.PPO``.

    Each rollout step follows Algorithm 1 of the paper with the bounded, scale-free law of
    CONTRACT.md section 1b: the policy samples ``a_t``, ESA probes a critic around it, and
    the env executes ``a_t + v(t)``, the shift before this step's update. The critic is a
    head quadratic in the action (:mod:`esa_client.common.quadratic_head`), fitted on the
    normalized GAE advantages of the last ``head_rollouts`` rollouts: ESA's shift converges
    to its maximum. ESA intervenes while the head passes ``EsaConfig.gate`` on a rollout it
    was not trained on (``esa/gate_correlation``, ``esa/active``), and fades over the
    budget of ``learn()`` (``EsaConfig.fade``; the default fades by half of it).

    ``v(t)`` does not depend on ``a_t``, so the executed action's behaviour density is the
    policy's translated by ``v(t)``: the rollout stores the executed action (unclipped, as
    SB3 stores its samples) with ``log pi_old(a_t)``, its exact behaviour log-probability.
    The update is PPO's with the decoupled objective of Hilton, Cobbe and Schulman (2022):
    the ratio is clipped around the collecting policy ``pi_old`` at the executed action and
    weighted by ``min(pi_old(x) / b(x), weight_cap)``, so a shift of a sizeable fraction of
    sigma does not fight the clip. Without a shift it is PPO's objective.

    ESA works in the policy's action space scaled to [-1, 1] by the Box bounds, so one
    ``EsaConfig`` means the same on every env; the trust region bounds the shift in units of
    the policy's standard deviation. ``squash_output`` policies are refused (a shifted
    squashed sample has no density under the policy), and so are Dict observations (the
    decoupled objective's buffer holds array observations: flatten them with gymnasium's
    ``FlattenObservation``). ``predict`` is unchanged: evaluation uses the plain policy. With
    ``EsaConfig(learning_rate=0)`` training is plain PPO with the same seed, bit for bit.

    Example::

        model = ESAPPO("MlpPolicy", "InvertedPendulum-v5")   # EsaConfig.ppo() by default
        model.learn(50_000)

    Args:
        policy: As for PPO.
        env: As for PPO.
        *args: Further positional arguments of PPO.
        **kwargs: The ``esa_*`` arguments of :class:`~esa_client.sb3.mixin.EsaMixin` (``esa``,
            default ``EsaConfig.ppo()``; ``esa_engine``, ``esa_address``, ``esa_control``,
            ...), and any other PPO argument.

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
    weight_cap = 2.0
    """The decoupled objective's cap on ``pi_old / b`` (>= 1)."""

    esa_head: nn.Module
    # Defaults until training (or a load) sets them; the scaling is read before _setup_model
    # when a model is loaded with an env (its session config is checked).
    _esa_scale: tuple[np.ndarray, np.ndarray] | None = None
    _esa_head_fitted = False
    _esa_active = False
    _esa_steps = 0

    @staticmethod
    def _default_esa() -> EsaConfig:
        return EsaConfig.ppo()

    def _setup_model(self) -> None:
        if isinstance(self.observation_space, spaces.Dict):
            raise ValueError(
                "expected array observations for ESAPPO (its decoupled objective's buffer "
                f"holds arrays), got {self.observation_space}: wrap the env in gymnasium's "
                "FlattenObservation, or train a plain PPO"
            )
        if self.rollout_buffer_class is None:
            self.rollout_buffer_class = EsaRolloutBuffer
        super()._setup_model()
        if self.policy.squash_output:
            raise ValueError(
                "expected a policy without squash_output for ESAPPO (the shifted sample "
                "must have a density under the policy), got squash_output=True"
            )
        if not isinstance(self.rollout_buffer, EsaRolloutBuffer):
            raise ValueError(
                "expected an EsaRolloutBuffer (or a subclass) as rollout_buffer_class, got "
                f"{type(self.rollout_buffer).__name__}"
            )
        features_dim = spaces.flatdim(self.observation_space)
        action_dim = int(np.prod(self.action_space.shape or ()))
        # A forked generator: building the critic must not move PPO's random stream.
        with th.random.fork_rng(devices=[]):
            self.esa_head = self._make_critic(features_dim, action_dim)
        self.esa_head.to(self.device)
        # fused: Adam's update of all tensors in one kernel (torch >= 2.4, CPU and CUDA).
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

    def _excluded_save_params(self) -> list[str]:
        # The critic's data come again from the next rollouts, the scaling from the space.
        return [*super()._excluded_save_params(), "_esa_head_data", "_esa_scale"]

    def _esa_space(self) -> tuple[np.ndarray | None, np.ndarray | None]:
        # PPO stores its Gaussian samples unclipped; ESA shifts them in that space too.
        return None, None

    def _esa_env_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        low, high = super()._esa_env_bounds()
        center, half_width = self._esa_scaling()
        return (low - center) / half_width, (high - center) / half_width

    def _esa_scaling(self) -> tuple[np.ndarray, np.ndarray]:
        """Center and half-width mapping the Box to [-1, 1] (0 and 1 where a side is open)."""
        if self._esa_scale is None:
            box = self._esa_box()
            low, high = box.low.reshape(-1), box.high.reshape(-1)
            bounded = np.isfinite(low) & np.isfinite(high)
            self._esa_scale = (
                np.where(bounded, (high + low) / 2, 0.0),
                np.where(bounded, (high - low) / 2, 1.0),
            )
        return self._esa_scale

    def _head_features(self, obs: th.Tensor) -> th.Tensor:
        """The observation as the critic sees it: preprocessed as SB3 does, flattened."""
        pre = preprocess_obs(obs, self.observation_space, self.policy.normalize_images)
        assert isinstance(pre, th.Tensor)  # Dict observations are refused in _setup_model
        return pre.flatten(1).float()

    def _esa_policy_step(self, obs: th.Tensor) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        """SB3's ``policy(obs)`` with ESA: ``(a_t + v(t), values, log pi(a_t))``."""
        distribution, values = self._policy_forward(obs)
        actions = distribution.get_actions()
        log_prob = distribution.log_prob(actions)
        strength = self._esa_strength() if self._esa_active else 0.0
        if strength > 0.0:
            gaussian = _gaussian(distribution)
            # SB3's Box distributions give the sample, mean and std flat, (N, D) each.
            sample = actions.cpu().numpy()
            mean, std = gaussian.mean.cpu().numpy(), gaussian.stddev.cpu().numpy()
            executed = self._esa_act(obs, sample, mean, std, strength)
            actions = th.from_numpy(executed).to(actions.device)
        return actions.reshape((-1, *self._esa_box().shape)), values, log_prob

    def _policy_forward(self, obs: th.Tensor) -> tuple[Distribution, th.Tensor]:
        """SB3's ``forward`` up to the sample, so that the sample draws what SB3's would."""
        policy = self.policy
        features = policy.extract_features(obs)
        if policy.share_features_extractor:
            latent_pi, latent_vf = policy.mlp_extractor(features)
        else:
            pi_features, vf_features = features
            latent_pi = policy.mlp_extractor.forward_actor(pi_features)
            latent_vf = policy.mlp_extractor.forward_critic(vf_features)
        return policy._get_action_dist_from_latent(latent_pi), policy.value_net(latent_vf)

    def _esa_act(
        self, obs: th.Tensor, sample: np.ndarray, mean: np.ndarray, std: np.ndarray, f: float
    ) -> np.ndarray:
        """The env's actions ``a_t + v(t)``, float32 ``(N, D)``, at ESA's strength ``f``."""
        starts = self._last_episode_starts
        assert starts is not None  # set by SB3 before its rollouts
        shift = self._esa_shift(obs, sample, mean, std, starts, f)
        if self.esa_control == "placebo":
            shift = self._placebo(shift, starts)
        if self._esa_steps % REPORT_EVERY == 0:
            self._record_shift(sample, shift, mean, std, f)
        self._esa_steps += 1
        return self._execute(sample, shift, std)

    def _execute(self, sample: np.ndarray, shift: np.ndarray, std: np.ndarray) -> np.ndarray:
        """What the env executes and the buffer stores: ``a_t + v(t)``.

        The sum in float64, cast back to the policy's float32.
        """
        executed: np.ndarray = (sample.astype(np.float64) + shift).astype(sample.dtype)
        return executed

    def _esa_shift(
        self,
        obs: th.Tensor,
        sample: np.ndarray,
        mean: np.ndarray,
        std: np.ndarray,
        starts: np.ndarray,
        f: float,
    ) -> np.ndarray:
        """ESA's shift ``v(t)`` (or the gradient control's) in the Box's units, float64 (N, D)."""
        center, half_width = self._esa_scaling()
        low, high = self._esa_env_bounds()
        units = np.maximum(std / half_width, SMALLEST_SCALE)
        critic = CriticAtStep(
            self.esa_head, self._head_features(obs), (mean - center) / half_width, units, low, high
        )
        scaled = (sample - center) / half_width
        if self.esa_control == "gradient":
            size = gradient_size(f, self.esa.trust_region)
            shift: np.ndarray = size * unit_gradient(critic.gradient(scaled)) * std
            return shift
        runtime = self._esa_runtime()
        applied = runtime.step(scaled, starts, self._closed_form(critic), units, strength=f)
        shift = (applied - scaled) * half_width
        return shift

    def _closed_form(self, critic: CriticAtStep) -> Any:
        """The critic the engine evaluates at the probes: the quadratic head's closed form."""
        return critic.closed_form()

    def _record_shift(
        self, sample: np.ndarray, shift: np.ndarray, mean: np.ndarray, std: np.ndarray, f: float
    ) -> None:
        box = self._esa_box()
        kappa = self.esa.trust_region
        bound = None if kappa is None else f * kappa
        report = shift_report(
            sample, shift, mean, std, box.low.reshape(-1), box.high.reshape(-1), bound
        )
        for key, value in report.items():
            self.logger.record_mean(f"esa/{key}", value)
        self.logger.record_mean("esa/strength", f)

    def collect_rollouts(
        self,
        env: VecEnv,
        callback: BaseCallback,
        rollout_buffer: RolloutBuffer,
        n_rollout_steps: int,
    ) -> bool:
        """SB3's ``OnPolicyAlgorithm.collect_rollouts`` with ESA's step in the policy's place.

        The env gets ``clip(a_t + v(t))``; the buffer stores ``a_t + v(t)`` unclipped with
        ``log pi(a_t)``.
        """
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
            with th.no_grad():
                obs_tensor = obs_as_tensor(self._last_obs, self.device)  # type: ignore[arg-type]
                actions_t, values, log_probs = self._esa_policy_step(obs_tensor)  # type: ignore[arg-type]
            actions = actions_t.cpu().numpy()
            # PPO's Gaussian is unbounded: the env gets the sample clipped to its Box.
            box = self._esa_box()
            clipped_actions = np.clip(actions, box.low, box.high)
            new_obs, rewards, dones, infos = env.step(clipped_actions)
            self.num_timesteps += env.num_envs
            callback.update_locals(locals())
            if not callback.on_step():
                return False
            self._update_info_buffer(infos, dones)
            n_steps += 1
            # A truncated episode bootstraps with the value of its last observation.
            for idx, done in enumerate(dones):
                if (
                    done
                    and infos[idx].get("terminal_observation") is not None
                    and infos[idx].get("TimeLimit.truncated", False)
                ):
                    terminal_obs = self.policy.obs_to_tensor(infos[idx]["terminal_observation"])[0]
                    with th.no_grad():
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
        with th.no_grad():
            values = self.policy.predict_values(obs_as_tensor(new_obs, self.device))  # type: ignore[arg-type]
        rollout_buffer.compute_returns_and_advantage(last_values=values, dones=dones)
        callback.update_locals(locals())
        callback.on_rollout_end()
        return True

    def train(self) -> None:
        """The gate on the new rollout, PPO's update, then the critic's fit.

        The update has the decoupled objective; the critic's fit draws from generators of its
        own, so PPO's random draws are SB3's.
        """
        self._check_gate()
        self._prepare_update()
        self._train_policy()
        self.logger.record("esa/head_loss", self._fit_critic())

    def _fit_critic(self) -> float:
        """Fits the critic on the kept rollouts; returns the mean loss."""
        return fit_critic(
            self.esa_head,
            self.esa_head_optimizer,
            self._esa_head_data,
            rng=self._esa_rng,
            epochs=self.head_epochs,
            batch_size=self.head_batch_size,
        )

    def _check_gate(self) -> None:
        """Scores the critic on the new rollout (which it has not seen), then keeps the rollout."""
        buffer = self.rollout_buffer
        obs = buffer.to_torch(buffer.observations.reshape(-1, *buffer.obs_shape))
        actions = buffer.to_torch(buffer.actions.reshape(-1, buffer.action_dim))
        advantages = buffer.to_torch(buffer.advantages.reshape(-1))
        with th.no_grad():
            # The policy that collected this rollout: train() has not updated it yet.
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

    def _prepare_update(self) -> None:
        """Stores ``log pi_old(x)`` of each executed action, for the decoupled objective."""
        buffer = cast(EsaRolloutBuffer, self.rollout_buffer)
        obs = buffer.to_torch(buffer.observations.reshape(-1, *buffer.obs_shape))
        actions = buffer.to_torch(buffer.actions.reshape(-1, buffer.action_dim))
        with th.no_grad():
            # The policy that collected the rollout: train() has not updated it yet.
            proximal = self.policy.get_distribution(obs).log_prob(actions)
        buffer.extras["proximal_log_prob"] = (
            proximal.cpu().numpy().reshape(buffer.buffer_size, buffer.n_envs)
        )

    def _policy_ratio(
        self, samples: EsaRolloutBufferSamples, log_prob: th.Tensor
    ) -> tuple[th.Tensor, th.Tensor | float]:
        """``(log of the reference density, weight)`` of the clipped objective.

        The decoupled objective's reference is the proximal policy ``pi_old`` at the
        executed action, weighted by ``pi_old / b`` (capped); PPO's is ``b`` itself.
        """
        reference = samples.extras["proximal_log_prob"].flatten()
        weight = th.exp(reference - samples.old_log_prob).clamp(max=self.weight_cap)
        return reference, weight

    def _optimizer_step(self, samples: EsaRolloutBufferSamples) -> None:
        """The policy's optimizer step, after PPO's gradient clipping."""
        self.policy.optimizer.step()

    def _train_policy(self) -> None:
        """SB3's ``PPO.train`` with the objective of :meth:`_policy_ratio`."""
        self.policy.set_training_mode(True)
        self._update_learning_rate(self.policy.optimizer)
        clip_range = self.clip_range(self._current_progress_remaining)  # type: ignore[operator]
        if self.clip_range_vf is not None:
            clip_range_vf = self.clip_range_vf(self._current_progress_remaining)  # type: ignore[operator]
        entropy_losses, pg_losses, value_losses, clip_fractions = [], [], [], []
        continue_training = True
        for epoch in range(self.n_epochs):
            approx_kl_divs = []
            for rollout_data in self.rollout_buffer.get(self.batch_size):
                samples = cast(EsaRolloutBufferSamples, rollout_data)
                values, log_prob, entropy = self.policy.evaluate_actions(
                    samples.observations, samples.actions
                )
                values = values.flatten()
                advantages = samples.advantages
                # Normalization does not make sense if mini batchsize == 1.
                if self.normalize_advantage and len(advantages) > 1:
                    advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
                reference, weight = self._policy_ratio(samples, log_prob)
                ratio = th.exp(log_prob - reference)
                policy_loss_1 = advantages * ratio
                policy_loss_2 = advantages * th.clamp(ratio, 1 - clip_range, 1 + clip_range)
                policy_loss = -(weight * th.min(policy_loss_1, policy_loss_2)).mean()
                pg_losses.append(policy_loss.item())
                clip_fraction = th.mean((th.abs(ratio - 1) > clip_range).float()).item()
                clip_fractions.append(clip_fraction)
                if self.clip_range_vf is None:
                    values_pred = values
                else:
                    values_pred = samples.old_values + th.clamp(
                        values - samples.old_values, -clip_range_vf, clip_range_vf
                    )
                value_loss = F.mse_loss(samples.returns, values_pred)
                value_losses.append(value_loss.item())
                if entropy is None:
                    entropy_loss = -th.mean(-log_prob)
                else:
                    entropy_loss = -th.mean(entropy)
                entropy_losses.append(entropy_loss.item())
                loss = policy_loss + self.ent_coef * entropy_loss + self.vf_coef * value_loss
                # Schulman's estimator of the KL to the policy the ratio is taken against.
                with th.no_grad():
                    log_ratio = log_prob - reference
                    approx_kl_div = th.mean((th.exp(log_ratio) - 1) - log_ratio).cpu().numpy()
                    approx_kl_divs.append(approx_kl_div)
                if self.target_kl is not None and approx_kl_div > 1.5 * self.target_kl:
                    continue_training = False
                    if self.verbose >= 1:
                        print(
                            f"Early stopping at step {epoch} due to reaching max kl: "
                            f"{approx_kl_div:.2f}"
                        )
                    break
                self.policy.optimizer.zero_grad()
                loss.backward()
                th.nn.utils.clip_grad_norm_(self.policy.parameters(), self.max_grad_norm)
                self._optimizer_step(samples)
            self._n_updates += 1
            if not continue_training:
                break
        explained_var = explained_variance(
            self.rollout_buffer.values.flatten(), self.rollout_buffer.returns.flatten()
        )
        self.logger.record("train/entropy_loss", np.mean(entropy_losses))
        self.logger.record("train/policy_gradient_loss", np.mean(pg_losses))
        self.logger.record("train/value_loss", np.mean(value_losses))
        self.logger.record("train/approx_kl", np.mean(approx_kl_divs))
        self.logger.record("train/clip_fraction", np.mean(clip_fractions))
        self.logger.record("train/loss", loss.item())
        self.logger.record("train/explained_variance", explained_var)
        if hasattr(self.policy, "log_std"):
            self.logger.record("train/std", th.exp(self.policy.log_std).mean().item())
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/clip_range", clip_range)
        if self.clip_range_vf is not None:
            self.logger.record("train/clip_range_vf", clip_range_vf)


def _gaussian(distribution: Distribution) -> th.distributions.Normal:
    """The torch Normal of a Box policy's action distribution.

    A Box policy without squashing (checked in ``_setup_model``) has a DiagGaussian or a gSDE
    distribution, both a ``Normal`` underneath; SB3 types the attribute for every kind.
    """
    return cast(th.distributions.Normal, distribution.distribution)
