"""``ESAPPO``: stable-baselines3 PPO whose sampled actions are improved by ESA."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3 import PPO
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.distributions import Distribution
from stable_baselines3.common.utils import obs_as_tensor
from stable_baselines3.common.vec_env import VecEnv
from torch.nn import functional as F

from ..config import EsaConfig
from .action_critic import ActionCritic
from .mixin import EsaMixin, tile_obs


class ESAPPO(EsaMixin, PPO):
    """PPO with Extremum-Seeking Action selection; a drop-in for ``stable_baselines3.PPO``.

    PPO has no action-value network to probe, so ESAPPO trains an auxiliary critic
    ``Q(s, a)`` (an MLP on the policy's detached value features and the action) on
    every rollout, regressing the rollout's lambda-returns (``RolloutBuffer.returns``,
    the targets PPO's value function also uses) on the actions that were applied.
    ESA probes that critic; the env receives the improved action, and the rollout
    stores the improved action with its log-probability recomputed under the
    behaviour policy, so PPO's ratio ``pi_new(a) / pi_old(a)`` is evaluated on the
    action actually taken. ESA starts with the second rollout, once the critic has
    been fitted once.

    ESA works in the policy's action space: the env's Box bounds (PPO's Gaussian
    actions are unsquashed), or [-1, 1] with ``squash_output`` (gSDE).
    ``predict`` is unchanged: evaluation uses the plain policy.

    Example::

        model = ESAPPO("MlpPolicy", "InvertedPendulum-v5", esa=EsaConfig(amplitude=0.2))
        model.learn(50_000)

    Args:
        policy: As for PPO.
        env: As for PPO.
        esa: The ESA hyperparameters (default ``EsaConfig()``).
        esa_address: An esa-server address (``host:port`` or ``unix:/path``); None
            spawns a private server that stops with the model (or ``esa_close()``).
        esa_q_net_arch: Hidden layers of the auxiliary critic.
        esa_q_learning_rate: Adam learning rate of the auxiliary critic.
        esa_q_epochs: Passes over each rollout when fitting the auxiliary critic
            (minibatches of PPO's ``batch_size``).
        **kwargs: Any other PPO argument.
    """

    def __init__(
        self,
        policy: Any,
        env: Any,
        *args: Any,
        esa: EsaConfig | None = None,
        esa_address: str | None = None,
        esa_q_net_arch: Sequence[int] = (64, 64),
        esa_q_learning_rate: float = 1e-3,
        esa_q_epochs: int = 5,
        **kwargs: Any,
    ) -> None:
        """Creates the PPO model and the auxiliary critic."""
        # Set before the SB3 constructor: its _setup_model builds the critic from them.
        self.esa_q_net_arch = tuple(esa_q_net_arch)
        self.esa_q_learning_rate = esa_q_learning_rate
        self.esa_q_epochs = esa_q_epochs
        self._esa_q_fitted = False
        super().__init__(policy, env, *args, esa=esa, esa_address=esa_address, **kwargs)

    def _setup_model(self) -> None:
        super()._setup_model()
        features_dim = self.policy.vf_features_extractor.features_dim
        action_dim = int(np.prod(self.action_space.shape))
        self.esa_q_net = ActionCritic(features_dim, action_dim, self.esa_q_net_arch).to(self.device)
        self.esa_q_optimizer = th.optim.Adam(
            self.esa_q_net.parameters(), lr=self.esa_q_learning_rate
        )

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts, variables = super()._get_torch_save_params()
        return [*state_dicts, "esa_q_net", "esa_q_optimizer"], variables

    def _esa_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        if self.policy.squash_output:
            dim = int(np.prod(self.action_space.shape))
            return -np.ones(dim), np.ones(dim)
        return self.action_space.low.reshape(-1), self.action_space.high.reshape(-1)

    def _esa_features(self, obs: Any) -> th.Tensor:
        with th.no_grad():
            return self.policy.extract_features(obs, self.policy.vf_features_extractor)

    def _sample(self, obs: Any) -> tuple[th.Tensor, th.Tensor, th.Tensor, Distribution, th.Tensor]:
        """``ActorCriticPolicy.forward`` that also returns the distribution and the value features.

        The ESA step evaluates the improved action's log-probability under this same
        distribution and probes the critic on these features: keeping them spares a
        second policy pass per step.
        """
        policy = self.policy
        with th.no_grad():
            features = policy.extract_features(obs)
            if policy.share_features_extractor:
                pi_features = vf_features = features
            else:
                pi_features, vf_features = features
            values = policy.value_net(policy.mlp_extractor.forward_critic(vf_features))
            latent_pi = policy.mlp_extractor.forward_actor(pi_features)
            distribution = policy._get_action_dist_from_latent(latent_pi)
            actions = distribution.get_actions()
            log_probs = distribution.log_prob(actions)
        actions = actions.reshape((-1, *self.action_space.shape))
        return actions, values, log_probs, distribution, vf_features

    def _esa_q_at(self, features: th.Tensor) -> Any:
        def q_fn(actions: np.ndarray) -> np.ndarray:
            reps = len(actions) // self.n_envs
            with th.no_grad():
                action_tensor = th.as_tensor(actions, dtype=th.float32, device=self.device)
                return self.esa_q_net(tile_obs(features, reps), action_tensor).cpu().numpy()

        return q_fn

    def _fit_esa_critic(self) -> None:
        losses = []
        for _ in range(self.esa_q_epochs):
            for data in self.rollout_buffer.get(self.batch_size):
                q = self.esa_q_net(self._esa_features(data.observations), data.actions)
                loss = F.mse_loss(q, data.returns)
                self.esa_q_optimizer.zero_grad()
                loss.backward()
                self.esa_q_optimizer.step()
                losses.append(loss.item())
        self.logger.record("esa/q_loss", float(np.mean(losses)))
        self._esa_q_fitted = True

    def train(self) -> None:
        """Fits the auxiliary critic on the rollout, then runs PPO's update."""
        self._fit_esa_critic()
        super().train()

    def collect_rollouts(
        self,
        env: VecEnv,
        callback: BaseCallback,
        rollout_buffer: RolloutBuffer,
        n_rollout_steps: int,
    ) -> bool:
        """SB3 2.9's ``OnPolicyAlgorithm.collect_rollouts`` with the ESA step inserted.

        Between sampling and stepping the env, the sampled actions are improved by ESA
        and their log-probabilities recomputed; everything else is SB3's loop.
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

            obs_tensor = obs_as_tensor(self._last_obs, self.device)
            actions, values, log_probs, distribution, features = self._sample(obs_tensor)
            actions = actions.cpu().numpy()

            if self._esa_q_fitted:
                improved = self._esa_runtime().improve(
                    actions.reshape(env.num_envs, -1),
                    self._last_episode_starts,
                    self._esa_q_at(features),
                )
                actions = improved.reshape(actions.shape).astype(actions.dtype)
                with th.no_grad():
                    log_probs = distribution.log_prob(th.as_tensor(actions, device=self.device))

            clipped_actions = actions
            if isinstance(self.action_space, spaces.Box):
                if self.policy.squash_output:
                    clipped_actions = self.policy.unscale_action(clipped_actions)
                else:
                    clipped_actions = np.clip(
                        actions, self.action_space.low, self.action_space.high
                    )

            new_obs, rewards, dones, infos = env.step(clipped_actions)

            self.num_timesteps += env.num_envs

            callback.update_locals(locals())
            if not callback.on_step():
                return False

            self._update_info_buffer(infos, dones)
            n_steps += 1

            # Bootstrap truncated episodes with the value function (SB3 issue #633).
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
                self._last_obs,
                actions,
                rewards,
                self._last_episode_starts,
                values,
                log_probs,
            )
            self._last_obs = new_obs
            self._last_episode_starts = dones

        with th.no_grad():
            values = self.policy.predict_values(obs_as_tensor(new_obs, self.device))

        rollout_buffer.compute_returns_and_advantage(last_values=values, dones=dones)

        callback.update_locals(locals())

        callback.on_rollout_end()

        return True
