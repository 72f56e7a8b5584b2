"""The research arms of ESAPPO: subclasses that override what the arm changes.

The product's ``ESAPPO`` is E2's ``ppo_esa``: the quadratic head, the decoupled objective,
the shift executed. The studies also ran (and their committed runs name) the linear head
(:class:`LinearHead`), a Q-network critic (:class:`QNetworkCritic`), PPO's clip-only
objective (:class:`ClipObjective`) and the target mode (:class:`TargetMode`), each a mixin
put before ``ESAPPO`` in the bases, as sb3-contrib extends SB3. :func:`esappo_class`
composes them from a run's stored options.
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING, Any, cast

import numpy as np
import torch as th
import torch.nn.functional as F
from esa_client.common.controls import gradient_size, unit_gradient
from esa_client.common.quadratic_head import CriticAtStep, mlp
from esa_client.sb3 import ESAPPO
from esa_client.sb3.esa_buffer import EsaRolloutBuffer, EsaRolloutBufferSamples
from esa_client.transports.base import LinearCritic
from gymnasium import spaces
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.distributions import Distribution
from stable_baselines3.common.preprocessing import is_image_space
from stable_baselines3.common.vec_env import VecEnv
from torch import nn

from esa_experiments.lab.linear_head import AdvantageHead, fit

if TYPE_CHECKING:
    # The mixins are always combined with ESAPPO (:func:`esappo_class`): checked as one.
    _Base = ESAPPO
else:
    _Base = object


class QNetwork(nn.Module):
    """``Q(s, z)``: a tanh MLP of the observation features and ``z = (a - mu) / sigma``.

    The paper's choice (Algorithm 1 probes a learned action-value network): any shape in the
    action, at the cost of a network forward pass per probe.

    Args:
        features_dim: Size of the (flattened) observation features.
        action_dim: Action dimension D.
        hidden: Hidden units of each of the two layers.
    """

    def __init__(self, features_dim: int, action_dim: int, hidden: int = 64) -> None:
        """Builds the network."""
        super().__init__()
        self.net = mlp(features_dim + action_dim, hidden, 1)

    def forward(self, features: th.Tensor, z: th.Tensor) -> th.Tensor:
        """Q for policy-normalized actions ``z``, shape ``(batch,)``."""
        value: th.Tensor = self.net(th.cat([features, z], dim=1)).squeeze(1)
        return value


class NetworkAtStep(CriticAtStep):
    """A Q-network at one step's states: the sessions evaluate it by torch at the probes."""

    def closed_form(self) -> Any:
        """The network itself (it has no closed form)."""
        return self


class QNetworkCritic(_Base):
    """ESA probes a Q-network of ``(s, z)``, evaluated by torch at the probes."""

    def _make_critic(self, features_dim: int, action_dim: int) -> nn.Module:
        return QNetwork(features_dim, action_dim, self.head_hidden)

    def _critic_at_step(self, obs: th.Tensor, mean: np.ndarray, std: np.ndarray) -> CriticAtStep:
        return NetworkAtStep(**vars(super()._critic_at_step(obs, mean, std)))


class LinearHead(_Base):
    """ESA probes the linear advantage head ``A = w(s) . z`` (:mod:`.linear_head`).

    Evaluated per step by the head's snapshot (:class:`.linear_head.HeadSnapshot`), taken
    again whenever a fit or a load changed the head; the engine steps its linear critic.
    """

    _esa_head_snapshot: Any = None

    def _make_critic(self, features_dim: int, action_dim: int) -> nn.Module:
        return AdvantageHead(features_dim, action_dim, self.head_hidden)

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "_esa_head_snapshot"]

    def _fit_critic(self) -> float:
        head = self.esa_head
        assert isinstance(head, AdvantageHead)
        return fit(
            head,
            self.esa_head_optimizer,
            rollouts=self._esa_head_data,
            rng=self._esa_rng,
            epochs=self.head_epochs,
            batch_size=self.head_batch_size,
        )

    def _esa_mlp(self) -> Any:
        """The head's snapshot, taken again whenever its parameters changed."""
        head = self.esa_head
        assert isinstance(head, AdvantageHead)
        version = head.version()
        if self._esa_head_snapshot is None or self._esa_head_snapshot[0] != version:
            self._esa_head_snapshot = (
                version,
                head.snapshot(self.esa_frame.center, self.esa_frame.half_width),
            )
        return self._esa_head_snapshot[1]

    def _step_features(self, obs: th.Tensor) -> np.ndarray:
        """The head's input at one step, in numpy (a float Box's observation as it is)."""
        space = self.observation_space
        if isinstance(space, spaces.Box) and not (
            self.policy.normalize_images and is_image_space(space)
        ):
            host: np.ndarray = obs.cpu().numpy().reshape(len(obs), -1)
            return host if host.dtype in (np.float32, np.float64) else host.astype(np.float32)
        features: np.ndarray = self._head_features(obs).cpu().numpy()
        return features

    def _session_shift(
        self,
        obs: th.Tensor,
        sample: np.ndarray,
        mean: np.ndarray,
        std: np.ndarray,
        starts: np.ndarray,
        f: float,
    ) -> np.ndarray:
        head = self._esa_mlp()
        scaled, gain, offset, units = head.step_inputs(self._step_features(obs), sample, mean, std)
        runtime = self._esa_runtime()
        applied = runtime.step(scaled, starts, LinearCritic(gain, offset), units, strength=f)
        shift: np.ndarray = head.shift(scaled, applied)
        return shift

    def _gradient_shift(
        self, obs: th.Tensor, sample: np.ndarray, mean: np.ndarray, std: np.ndarray, f: float
    ) -> np.ndarray:
        weights = self._esa_mlp().weights(self._step_features(obs))
        shift: np.ndarray = gradient_size(f, self.esa.trust_region) * unit_gradient(weights) * std
        return shift


class ClipObjective(_Base):
    """PPO's clipped objective, its ratio taken against the behaviour density ``b``."""

    def _policy_ratio(
        self, samples: EsaRolloutBufferSamples, log_prob: th.Tensor
    ) -> tuple[th.Tensor, th.Tensor | float]:
        return samples.old_log_prob, 1.0


class TargetMode(_Base):
    """ESA as an improvement target instead of behaviour.

    The env executes the policy's own sample (exact on-policy data) while the sessions still
    run on it, and a bounded auxiliary loss in PPO's minibatch loop pulls the policy mean
    toward ``mu_old(s) + v_t`` in units of ``sigma_old`` (dual policy iteration's
    improve-then-project step): a one-sided Huber loss of the shortfall
    ``max(0, sign(z) (z - (mu - mu_old) / sigma_old))``, ``z = v_t / sigma_old``, over the
    samples ESA shifted, weighted by ``target_weight``, after PPO's gradient clipping.
    """

    target_weight = 1.0
    _esa_targets: np.ndarray
    _esa_targeted = False
    _esa_target_losses: list[float]
    _esa_minibatch: EsaRolloutBufferSamples

    def _excluded_save_params(self) -> list[str]:
        # One rollout's bookkeeping, made again by the next.
        excluded = ["_esa_targets", "_esa_targeted", "_esa_target_losses", "_esa_minibatch"]
        return [*super()._excluded_save_params(), *excluded]

    def collect_rollouts(
        self,
        env: VecEnv,
        callback: BaseCallback,
        rollout_buffer: RolloutBuffer,
        n_rollout_steps: int,
    ) -> bool:
        """ESAPPO's rollout, each step's shift in units of sigma kept as its target."""
        assert isinstance(rollout_buffer, EsaRolloutBuffer)
        dim = self.esa_frame.dim
        shape = (rollout_buffer.buffer_size, rollout_buffer.n_envs, dim)
        self._esa_targets = np.zeros(shape, dtype=np.float32)
        done: bool = super().collect_rollouts(env, callback, rollout_buffer, n_rollout_steps)
        # After the buffer's reset at the rollout's start, which empties its extras.
        rollout_buffer.extras["esa_target"] = self._esa_targets
        return done

    def _session_shift(
        self,
        obs: th.Tensor,
        sample: np.ndarray,
        mean: np.ndarray,
        std: np.ndarray,
        starts: np.ndarray,
        f: float,
    ) -> np.ndarray:
        return self._targeted(super()._session_shift(obs, sample, mean, std, starts, f), std)

    def _gradient_shift(
        self, obs: th.Tensor, sample: np.ndarray, mean: np.ndarray, std: np.ndarray, f: float
    ) -> np.ndarray:
        return self._targeted(super()._gradient_shift(obs, sample, mean, std, f), std)

    def _targeted(self, shift: np.ndarray, std: np.ndarray) -> np.ndarray:
        """Keeps ``shift`` in units of sigma as this step's target; the env executes ``a_t``."""
        self._esa_targets[self.rollout_buffer.pos] = shift / std
        return np.zeros_like(shift)

    def train(self) -> None:
        """The old policy's mean and std kept for the target loss, ESAPPO's update, its log."""
        self._keep_old_policy()
        super().train()
        if self._esa_target_losses:
            self.logger.record("esa/target_loss", float(np.mean(self._esa_target_losses)))

    def _keep_old_policy(self) -> None:
        buffer = self.rollout_buffer
        assert isinstance(buffer, EsaRolloutBuffer)
        targets = buffer.extras["esa_target"]
        self._esa_targeted = bool(np.any(targets != 0))
        self._esa_target_losses = []
        if not self._esa_targeted:
            return
        flat = (buffer.buffer_size, buffer.n_envs)
        obs = buffer.to_torch(buffer.observations.reshape(-1, *buffer.obs_shape))
        with th.no_grad():
            old = _normal(self.policy.get_distribution(obs))
            for name, values in (("old_mean", old.mean), ("old_std", old.stddev)):
                buffer.extras[name] = values.cpu().numpy().reshape(*flat, -1)
        shifted = np.abs(targets[np.any(targets != 0, axis=2)])
        self.logger.record("esa/target_shift_over_std", float(shifted.mean()))

    def _setup_model(self) -> None:
        super()._setup_model()
        # The target loss's gradient joins PPO's after its gradient clipping, just before
        # the policy's optimizer steps on the minibatch _policy_ratio last saw.
        self.policy.optimizer.register_step_pre_hook(lambda *_: self._add_target_gradient())

    def _policy_ratio(
        self, samples: EsaRolloutBufferSamples, log_prob: th.Tensor
    ) -> tuple[th.Tensor, th.Tensor | float]:
        self._esa_minibatch = samples
        return super()._policy_ratio(samples, log_prob)

    def _add_target_gradient(self) -> None:
        if self._esa_targeted:
            self._esa_target_losses.extend(self._target_loss(self._esa_minibatch))

    def _target_loss(self, samples: EsaRolloutBufferSamples) -> list[float]:
        """Back-propagates the loss on a minibatch's shifted samples; returns it (or nothing)."""
        z = samples.extras["esa_target"]
        shifted = (z != 0).any(dim=1)
        if not bool(shifted.any()):
            return []
        obs = samples.observations[shifted]
        mu_old = samples.extras["old_mean"][shifted]
        sigma_old = samples.extras["old_std"][shifted]
        new = _normal(self.policy.get_distribution(obs))
        moved = (new.mean.reshape(len(obs), -1) - mu_old) / sigma_old
        target = z[shifted]
        # One-sided: only the part of the target the mean has not yet covered. A symmetric
        # loss toward mu_old + v anchored the policy at mu_old (v is a fraction of sigma)
        # and stalled PPO: return 116 against 457 on InvertedPendulum-v5 with v ~ 0.001 sigma.
        shortfall = F.relu(th.sign(target) * (target - moved))
        loss = self.target_weight * F.smooth_l1_loss(shortfall, th.zeros_like(shortfall))
        loss.backward()
        return [loss.item()]


def _normal(distribution: Distribution) -> th.distributions.Normal:
    """The torch Normal under a Box policy's distribution (ESAPPO refuses squashed ones)."""
    return cast(th.distributions.Normal, distribution.distribution)


CRITICS: dict[str, type] = {"linear": LinearHead, "quadratic": object, "qnet": QNetworkCritic}
OBJECTIVES: dict[str, type] = {"clip": ClipObjective, "decoupled": object}
MODES: dict[str, type] = {"behaviour": object, "target": TargetMode}


@functools.cache
def esappo_class(
    critic: str = "quadratic",
    objective: str = "decoupled",
    mode: str = "behaviour",
    target_weight: float = 1.0,
) -> type[ESAPPO]:
    """ESAPPO with the arm's critic, objective and mode (the product's when all default).

    Raises:
        ValueError: For an unknown critic, objective or mode.
    """
    parts = []
    # The mode first: its update extends the objective's (ClipObjective's needs nothing).
    for name, value, table in (
        ("mode", mode, MODES),
        ("objective", objective, OBJECTIVES),
        ("critic", critic, CRITICS),
    ):
        if value not in table:
            raise ValueError(f"expected {name} in {tuple(table)}, got {value!r}")
        if table[value] is not object:
            parts.append(table[value])
    if not parts:
        return ESAPPO
    name = "".join(part.__name__ for part in parts) + "ESAPPO"
    attributes = {"target_weight": target_weight} if mode == "target" else {}
    return type(name, (*parts, ESAPPO), attributes)
