"""``ESASAC``: stable-baselines3 SAC whose exploratory actions are shifted by ESA."""

from __future__ import annotations

from typing import Any

import torch as th
from stable_baselines3 import SAC

from .off_policy import OffPolicyEsaMixin

__all__ = ["ESASAC"]


class ESASAC(OffPolicyEsaMixin, SAC):
    """SAC with Extremum-Seeking Action selection; a drop-in for ``stable_baselines3.SAC``.

    ESA works in SAC's squashed action space [-1, 1], where the action scale is the
    policy's local standard deviation ``min((1 - tanh(mu)^2) std, 1)``. The gate
    (``EsaConfig.gate``), checked every ``gate_every`` steps after ``learning_starts``, is
    the rank correlation of the critic's ``Q(s, a) - Q(s, mu)`` with the one-step advantage
    ``r + gamma V(s') - V(s)``, ``V(s) = Q(s, mu)``, on the transitions since the last
    check; with ``gate=None`` ESA starts at ``learning_starts``. ``predict`` is SAC's.

    Args:
        *args: SAC's positional arguments (``policy``, ``env``, ...).
        **kwargs: The ``esa_*`` arguments of :class:`~esa_client.sb3.mixin.EsaMixin` (``esa``
            default ``EsaConfig.off_policy()``), and any other SAC argument.

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
        """The squashed mean and std, ``(1 - tanh(mu)^2) std`` capped at 1, in [-1, 1] units.

        ``std`` is read from the actor's distribution, not ``log_std``: under gSDE that holds
        the noise weights' scales.
        """
        std = self.actor.action_dist.distribution.stddev
        squashed = th.tanh(mean)
        return squashed, ((1.0 - squashed**2) * std).clamp(max=1.0)
