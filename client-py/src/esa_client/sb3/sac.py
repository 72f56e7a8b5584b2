"""``ESASAC``: stable-baselines3 SAC whose exploratory actions are shifted by ESA."""

from __future__ import annotations

from typing import Any

import torch as th
from stable_baselines3 import SAC

from .off_policy import OffPolicyEsaMixin

__all__ = ["ESASAC"]


class ESASAC(OffPolicyEsaMixin, SAC):
    """SAC with Extremum-Seeking Action selection; a drop-in for ``stable_baselines3.SAC``.

    Each step, for every env of the VecEnv (one ESA session each), the action SAC
    samples is probed with a sinusoidal perturbation, a critic scores the probes and the
    env executes ``a_t + v(t)`` (Algorithm 1), which is also what the replay buffer
    stores. ESA works in SAC's squashed action space: probes, shifts and amplitudes are
    in [-1, 1] units, and the action scale is the policy's local standard deviation
    there, ``min((1 - tanh(mu)^2) std, 1)``.

    ESA waits until the critic has learned something about actions (``EsaConfig.gate``):
    every ``gate_every`` steps after ``learning_starts`` it computes, on the transitions
    collected since the last check, the rank correlation between the critic's
    ``Q(s, a) - Q(s, mu)`` and the one-step advantage ``r + gamma V(s') - V(s)`` with
    ``V(s) = Q(s, mu)``. With ``gate=None`` ESA starts at ``learning_starts``. With
    ``EsaConfig(fade=...)`` ESA's shift fades to 0 over that fraction of the budget of
    ``learn()``. The controls (``esa_control``) are :class:`OffPolicyEsaMixin`'s.

    With ``EsaConfig(learning_rate=0)`` the shift stays 0 and training equals plain SAC
    step for step (the gate and the probes draw no random numbers). ``predict`` is
    unchanged: evaluation uses the plain policy. The off-policy default is
    ``EsaConfig.off_policy()``, used when ``esa`` is not given.

    Example::

        model = ESASAC("MlpPolicy", "Pendulum-v1")
        model.learn(10_000)

    Args:
        policy: As for SAC.
        env: As for SAC.
        *args: Further positional arguments of SAC.
        **kwargs: The ``esa_*`` arguments of :class:`~esa_client.sb3.mixin.EsaMixin` (``esa``,
            default ``EsaConfig.off_policy()``; ``esa_client``, ``esa_on_unavailable``,
            ``esa_control``, ...), and any other SAC argument.

    Raises:
        ValueError: If the action space is not a Box, ``esa_control`` is unknown, or an
            ESA setting is invalid for this env.
    """

    def _policy_mean_and_std(self, obs: Any) -> tuple[th.Tensor, th.Tensor]:
        with th.no_grad():
            mean, log_std, extra = self.actor.get_action_dist_params(obs)
            self.actor.action_dist.proba_distribution(mean, log_std, **extra)
            return self._squashed(mean)

    def _policy_sample(self, obs: Any) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        # As SAC's Actor.forward: the sample from the same distribution parameters.
        mean, log_std, extra = self.actor.get_action_dist_params(obs)
        actions = self.actor.action_dist.actions_from_params(
            mean, log_std, deterministic=False, **extra
        )
        return (actions, *self._squashed(mean))

    def _squashed(self, mean: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """The squashed policy's mean action and its standard deviation in [-1, 1] units.

        The std is tanh's linearization at the mean, ``(1 - tanh(mu)^2) std``, capped at 1:
        no distribution on [-1, 1] spreads wider than that. ``std`` is the Gaussian's that
        the actor's distribution was last given: read there, not from ``log_std``, because
        under gSDE ``log_std`` holds the noise weights' scales and the std depends on the
        state.
        """
        std = self.actor.action_dist.distribution.stddev
        squashed = th.tanh(mean)
        return squashed, ((1.0 - squashed**2) * std).clamp(max=1.0)
