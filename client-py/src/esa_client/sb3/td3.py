"""``ESATD3``: stable-baselines3 TD3 whose noisy actions are shifted by ESA."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch as th
from stable_baselines3 import TD3
from stable_baselines3.common.noise import NormalActionNoise

from .off_policy import OffPolicyEsaMixin


class ESATD3(OffPolicyEsaMixin, TD3):
    """TD3 with Extremum-Seeking Action selection; a drop-in for ``stable_baselines3.TD3``.

    ``a_t`` is TD3's action plus its exploration noise, in the squashed space [-1, 1]; TD3
    has no policy distribution, so the action scale sigma is the noise's (a
    ``NormalActionNoise``'s sigma), or ``esa_action_scale``. The rest is ESASAC's.

    Args:
        esa_action_scale: sigma in [-1, 1] units (> 0, at most 1); None reads it from a
            ``NormalActionNoise`` and is 0.1 (RL Zoo's TD3 noise) without one.
        **kwargs: The ``esa_*`` arguments of :class:`~esa_client.sb3.mixin.EsaMixin`, and
            any other TD3 argument.

    Raises:
        ValueError: As for ESASAC, or for an ``esa_action_scale`` outside (0, 1].
    """

    def __init__(
        self,
        policy: Any,
        env: Any,
        *args: Any,
        esa_action_scale: float | None = None,
        **kwargs: Any,
    ) -> None:
        """Creates the TD3 model; the ESA sessions are created when training starts."""
        if esa_action_scale is not None and not 0 < esa_action_scale <= 1:
            raise ValueError(f"expected esa_action_scale in (0, 1], got {esa_action_scale!r}")
        self.esa_action_scale = esa_action_scale
        super().__init__(policy, env, *args, **kwargs)

    def _sigma(self) -> np.ndarray:
        """The action scale per dimension."""
        dim = int(np.prod(self.action_space.shape or ()))
        if self.esa_action_scale is not None:
            return np.full(dim, self.esa_action_scale)
        if isinstance(self.action_noise, NormalActionNoise):
            # A copy: broadcast_to's read-only view would reach torch, which warns on it.
            sigma = np.asarray(self.action_noise._sigma, dtype=np.float64)
            return np.array(np.broadcast_to(sigma, (dim,)))
        return np.full(dim, 0.1)

    def _policy_mean_and_std(self, obs: Any) -> tuple[th.Tensor, th.Tensor]:
        """The actor's action and the exploration noise's sigma, both in [-1, 1] units."""
        with th.no_grad():
            mean = self.actor(obs)
        return mean, self._noise_std(len(mean))

    def _policy_sample(self, obs: Any) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        # TD3's policy samples its mean: the noise is added after predict.
        mean, std = self._policy_mean_and_std(obs)
        return mean, mean, std

    def _noise_std(self, n: int) -> th.Tensor:
        """The exploration noise's sigma for ``n`` observations: no actor call is needed."""
        sigma = th.as_tensor(self._sigma(), dtype=th.float32, device=self.device)
        return sigma.expand(n, -1).clamp(min=1e-6, max=1.0)
