"""``DecoupledPPO``: PPO whose clipped objective is decoupled from the behaviour policy.

With a shifted action, the ratio against its behaviour density ``b`` fights PPO's clip. The
decoupled objective (Hilton, Cobbe and Schulman 2022, "Batch size-invariance for policy
optimization") clips the ratio around the proximal policy ``pi_old`` (the one that collected
the rollout) at the executed action and weights it by ``min(pi_old / b, weight_cap)``.
"""

from __future__ import annotations

from typing import cast

import numpy as np
import torch as th
import torch.nn.functional as F
from gymnasium import spaces
from stable_baselines3 import PPO
from stable_baselines3.common.utils import explained_variance

from .esa_buffer import EsaRolloutBuffer, EsaRolloutBufferSamples


class DecoupledPPO(PPO):
    """PPO with the decoupled objective; its rollout buffer keeps ``log pi_old`` per sample.

    Subclasses store, as each sample's action, what the env executed, and as its
    ``log_prob`` the behaviour log-probability of that action.

    Raises:
        ValueError: For Dict observations (the buffer holds arrays: flatten them with
            gymnasium's ``FlattenObservation``), or a rollout buffer class that is not an
            ``EsaRolloutBuffer``.
    """

    weight_cap = 2.0
    """The cap on ``pi_old / b`` (>= 1)."""

    def _setup_model(self) -> None:
        if isinstance(self.observation_space, spaces.Dict):
            raise ValueError(
                f"expected array observations for {type(self).__name__} (its rollout buffer "
                f"holds arrays), got {self.observation_space}: wrap the env in gymnasium's "
                "FlattenObservation, or train a plain PPO"
            )
        if self.rollout_buffer_class is None:
            self.rollout_buffer_class = EsaRolloutBuffer
        super()._setup_model()
        if not isinstance(self.rollout_buffer, EsaRolloutBuffer):
            raise ValueError(
                "expected an EsaRolloutBuffer (or a subclass) as rollout_buffer_class, got "
                f"{type(self.rollout_buffer).__name__}"
            )

    def _policy_ratio(
        self, samples: EsaRolloutBufferSamples, log_prob: th.Tensor
    ) -> tuple[th.Tensor, th.Tensor | float]:
        """``(log of the reference density, weight)``: ``pi_old`` and its capped ``pi_old / b``."""
        reference = samples.extras["proximal_log_prob"].flatten()
        weight = th.exp(reference - samples.old_log_prob).clamp(max=self.weight_cap)
        return reference, weight

    def train(self) -> None:
        """SB3's ``PPO.train`` with the objective of :meth:`_policy_ratio`."""
        # log pi_old(x) of each executed action, before pi is updated.
        buffer = cast(EsaRolloutBuffer, self.rollout_buffer)
        obs = buffer.to_torch(buffer.observations.reshape(-1, *buffer.obs_shape))
        actions = buffer.to_torch(buffer.actions.reshape(-1, buffer.action_dim))
        with th.no_grad():
            proximal = self.policy.get_distribution(obs).log_prob(actions)
        buffer.extras["proximal_log_prob"] = (
            proximal.cpu().numpy().reshape(buffer.buffer_size, buffer.n_envs)
        )
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
                self.policy.optimizer.step()
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
