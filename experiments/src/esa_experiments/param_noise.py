"""Adaptive parameter-space noise for SB3 PPO and SAC.

Plappert et al., "Parameter Space Noise for Exploration", ICLR 2018
(https://openreview.net/forum?id=ByBAl2eAZ). Instead of (only) adding noise to
the sampled actions, exploration comes from a perturbed copy of the policy:
every actor weight gets independent Gaussian noise ``N(0, sigma^2)``. Because
the effect of a given ``sigma`` on the actions changes as the network trains,
``sigma`` is adapted so that the action-space distance between the perturbed
and the unperturbed policy,

    d = sqrt(mean_{s, i} (mu_perturbed(s)_i - mu(s)_i)^2),

tracks a target ``delta``: ``sigma <- sigma * c`` if ``d < delta`` else
``sigma <- sigma / c`` (c = 1.01 in the paper and OpenAI baselines).

Implementation choices (the paper leaves them open for PPO and SAC):

* Only the weights that produce the action mean are perturbed
  (PPO: ``mlp_extractor.policy_net`` and ``action_net``; SAC: ``actor.latent_pi``
  and ``actor.mu``). The state-independent ``log_std`` of PPO and the
  ``log_std`` head of SAC are left alone, so parameter noise adds to the
  policy's own Gaussian exploration instead of replacing it. The paper uses
  layer normalization to make one ``sigma`` fit every layer; SB3's MLPs have
  none, so the adaptation alone sets the scale.
* PPO (on-policy, Section 3 of the paper): one perturbation ``eps`` per
  rollout. The rollout is collected with ``theta + eps`` and the PPO update is
  computed at ``theta + eps`` too (log-probabilities, ratios and gradients all
  under the perturbed policy, the paper's reparameterization of
  ``theta~ = theta + eps``); the update is then carried back to ``theta`` by
  subtracting ``eps``. ``sigma`` is adapted once per rollout on the rollout's
  observations.
* SAC (off-policy, like the paper's DDPG): actions are sampled from a
  perturbed copy of the actor, resampled at every episode end; training
  updates the unperturbed actor from the replay buffer as usual. ``sigma`` is
  adapted every ``adaptation_interval`` steps on a replay batch (50 as in
  OpenAI baselines).

Evaluation must use the unperturbed policy: use
:func:`esa_client.compare.evaluation.noise_free` around it.
"""

from __future__ import annotations

import contextlib
import copy
import math
from collections.abc import Iterator, Mapping
from typing import Any, cast

import numpy as np
import torch as th
from stable_baselines3 import PPO, SAC
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.vec_env import VecEnv
from stable_baselines3.sac.policies import Actor

Perturbation = dict[str, th.Tensor]


class AdaptiveParamNoise:
    """The adaptive scale ``sigma`` of the parameter noise and how to draw it.

    Args:
        initial_stddev: starting ``sigma``.
        desired_action_stddev: target action-space distance ``delta``.
        adaptation_coefficient: multiplicative step ``c > 1`` of ``sigma``.
        seed: seed of the noise generator (``None`` = nondeterministic).
    """

    def __init__(
        self,
        initial_stddev: float = 0.1,
        desired_action_stddev: float = 0.1,
        adaptation_coefficient: float = 1.01,
        seed: int | None = None,
    ) -> None:
        """Validates the settings and seeds the generator."""
        for name, value in (
            ("initial_stddev", initial_stddev),
            ("desired_action_stddev", desired_action_stddev),
        ):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"expected {name} finite and > 0, got {value}")
        if not (math.isfinite(adaptation_coefficient) and adaptation_coefficient > 1):
            raise ValueError(
                f"expected adaptation_coefficient finite and > 1, got {adaptation_coefficient}"
            )
        self.sigma = float(initial_stddev)
        self.desired_action_stddev = float(desired_action_stddev)
        self.adaptation_coefficient = float(adaptation_coefficient)
        self._generator = th.Generator()
        if seed is None:
            self._generator.seed()
        else:
            self._generator.manual_seed(seed)

    def adapt(self, distance: float) -> float:
        """Moves ``sigma`` one step toward the target distance; returns the new ``sigma``."""
        if not math.isfinite(distance):
            raise ValueError(f"expected a finite action distance, got {distance}")
        if distance < self.desired_action_stddev:
            self.sigma *= self.adaptation_coefficient
        else:
            self.sigma /= self.adaptation_coefficient
        return self.sigma

    def adapt_to(self, perturbed: th.Tensor, clean: th.Tensor, logger: Logger) -> None:
        """Adapts ``sigma`` to the distance between two batches of mean actions and logs both."""
        distance = action_distance(perturbed, clean)
        self.adapt(distance)
        logger.record("param_noise/distance", distance)
        logger.record("param_noise/sigma", self.sigma)

    def sample(self, parameters: Mapping[str, th.Tensor]) -> Perturbation:
        """Draws ``eps ~ N(0, sigma^2 I)`` shaped like each of ``parameters``."""
        return {
            name: th.randn(p.shape, generator=self._generator, dtype=p.dtype).to(p.device)
            * self.sigma
            for name, p in parameters.items()
        }


def action_distance(a: th.Tensor, b: th.Tensor) -> float:
    """Root-mean-square distance between two batches of actions (Plappert et al., Eq. 2)."""
    return float(th.sqrt(th.mean((a - b) ** 2)))


def _named(module_by_prefix: dict[str, th.nn.Module]) -> dict[str, th.nn.Parameter]:
    return {
        f"{prefix}.{name}": p
        for prefix, module in module_by_prefix.items()
        for name, p in module.named_parameters()
    }


@contextlib.contextmanager
def _shifted(
    parameters: dict[str, th.nn.Parameter], eps: Perturbation, sign: float
) -> Iterator[None]:
    """Adds ``sign * eps`` to the parameters in place, and undoes it on exit."""
    with th.no_grad():
        for name, p in parameters.items():
            p.add_(eps[name], alpha=sign)
    try:
        yield
    finally:
        with th.no_grad():
            for name, p in parameters.items():
                p.sub_(eps[name], alpha=sign)


class PPOParamNoise(PPO):
    """PPO whose rollouts come from an adaptively perturbed actor (see module docs).

    Args:
        *args: passed to :class:`stable_baselines3.PPO`.
        param_noise: keyword arguments of :class:`AdaptiveParamNoise`
            (``initial_stddev``, ``desired_action_stddev``, ``adaptation_coefficient``).
        **kwargs: passed to :class:`stable_baselines3.PPO`.
    """

    def __init__(
        self, *args: Any, param_noise: dict[str, float] | None = None, **kwargs: Any
    ) -> None:
        """Creates the PPO model; the noise is set up with the model."""
        self.param_noise_kwargs = dict(param_noise or {})
        super().__init__(*args, **kwargs)

    def _setup_model(self) -> None:
        super()._setup_model()
        self.param_noise = AdaptiveParamNoise(**self.param_noise_kwargs, seed=self.seed)
        self._eps: Perturbation | None = None
        self._eps_applied = False

    def _actor_parameters(self) -> dict[str, th.nn.Parameter]:
        return _named(
            {
                "mlp_extractor.policy_net": self.policy.mlp_extractor.policy_net,
                "action_net": self.policy.action_net,
            }
        )

    @contextlib.contextmanager
    def _shift(self, sign: float) -> Iterator[None]:
        if self._eps is None:
            yield
            return
        applied = self._eps_applied
        with _shifted(self._actor_parameters(), self._eps, sign):
            self._eps_applied = sign > 0
            try:
                yield
            finally:
                self._eps_applied = applied

    def unperturbed(self) -> contextlib.AbstractContextManager[None]:
        """Temporarily removes the perturbation if it is applied (i.e. inside a rollout)."""
        return self._shift(-1.0) if self._eps_applied else contextlib.nullcontext()

    def _mean_actions(self, obs: th.Tensor) -> th.Tensor:
        # A Box policy's distribution (DiagGaussian or gSDE) is a Normal; SB3 types it for all.
        return cast(th.distributions.Normal, self.policy.get_distribution(obs).distribution).mean

    def _adapt(self) -> None:
        obs = th.as_tensor(self.rollout_buffer.observations, device=self.device)
        obs = obs.reshape(-1, *(self.observation_space.shape or ()))
        with th.no_grad():
            clean = self._mean_actions(obs)
            with self._shift(+1.0):
                noisy = self._mean_actions(obs)
        self.param_noise.adapt_to(noisy, clean, self.logger)

    def collect_rollouts(
        self,
        env: VecEnv,
        callback: BaseCallback,
        rollout_buffer: RolloutBuffer,
        n_rollout_steps: int,
    ) -> bool:
        """Collects a rollout with a freshly perturbed actor."""
        self._eps = self.param_noise.sample(self._actor_parameters())
        with self._shift(+1.0):
            return super().collect_rollouts(env, callback, rollout_buffer, n_rollout_steps)

    def train(self) -> None:
        """Runs the PPO update at the perturbed parameters, then adapts ``sigma``."""
        with self._shift(+1.0):
            super().train()
        # Adapt after the update so the distance is measured for the policy
        # the next perturbation will be added to.
        self._adapt()

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "param_noise", "_eps", "_eps_applied"]


class SACParamNoise(SAC):
    """SAC that acts with an adaptively perturbed copy of its actor (see module docs).

    Args:
        *args: passed to :class:`stable_baselines3.SAC`.
        param_noise: keyword arguments of :class:`AdaptiveParamNoise`.
        adaptation_interval: env steps between two adaptations of ``sigma``.
        **kwargs: passed to :class:`stable_baselines3.SAC`.
    """

    def __init__(
        self,
        *args: Any,
        param_noise: dict[str, float] | None = None,
        adaptation_interval: int = 50,
        **kwargs: Any,
    ) -> None:
        """Creates the SAC model; the perturbed actor is set up with the model."""
        if adaptation_interval < 1:
            raise ValueError(f"expected adaptation_interval >= 1, got {adaptation_interval}")
        self.param_noise_kwargs = dict(param_noise or {})
        self.adaptation_interval = adaptation_interval
        super().__init__(*args, **kwargs)

    def _setup_model(self) -> None:
        super()._setup_model()
        self.param_noise = AdaptiveParamNoise(**self.param_noise_kwargs, seed=self.seed)
        self._perturbed_actor = copy.deepcopy(self.actor)
        self._perturb()

    @staticmethod
    def _actor_parameters(actor: Actor) -> dict[str, th.nn.Parameter]:
        return _named({"latent_pi": actor.latent_pi, "mu": actor.mu})

    def _perturb(self) -> None:
        """Loads ``theta + eps`` (fresh ``eps``) into the acting copy."""
        clean = self._actor_parameters(self.actor)
        eps = self.param_noise.sample(clean)
        with th.no_grad():
            for name, p in self._actor_parameters(self._perturbed_actor).items():
                p.copy_(clean[name] + eps[name])

    def _sample_action(
        self,
        learning_starts: int,
        action_noise: Any = None,
        n_envs: int = 1,
    ) -> tuple[np.ndarray, np.ndarray]:
        # SACPolicy._predict acts with policy.actor; training uses self.actor,
        # which keeps pointing at the unperturbed network.
        clean_actor = self.policy.actor
        self.policy.actor = self._perturbed_actor
        try:
            return super()._sample_action(learning_starts, action_noise, n_envs)
        finally:
            self.policy.actor = clean_actor

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
        if self.num_timesteps % self.adaptation_interval == 0 and replay_buffer.size() > 0:
            self._adapt(replay_buffer)
        if np.any(dones):
            self._perturb()

    def _adapt(self, replay_buffer: Any) -> None:
        obs = replay_buffer.sample(self.batch_size, env=self._vec_normalize_env).observations
        with th.no_grad():
            clean = self.actor(obs, deterministic=True)
            noisy = self._perturbed_actor(obs, deterministic=True)
        self.param_noise.adapt_to(noisy, clean, self.logger)

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "param_noise", "_perturbed_actor"]
