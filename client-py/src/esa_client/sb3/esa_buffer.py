"""ESAPPO's rollout buffer: SB3's, with named per-sample extras served with each minibatch."""

from __future__ import annotations

from collections.abc import Generator
from typing import NamedTuple

import numpy as np
import torch as th
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.vec_env import VecNormalize


class EsaRolloutBufferSamples(NamedTuple):
    """SB3's ``RolloutBufferSamples`` and the minibatch's extras, by name."""

    observations: th.Tensor
    actions: th.Tensor
    old_values: th.Tensor
    old_log_prob: th.Tensor
    advantages: th.Tensor
    returns: th.Tensor
    extras: dict[str, th.Tensor]


class EsaRolloutBuffer(RolloutBuffer):
    """A ``RolloutBuffer`` that also holds ``extras``: arrays shaped ``(n_steps, n_envs, ...)``.

    What ESAPPO's update needs per sample beyond PPO's fields (e.g. the proximal
    log-probability), indexed with the same minibatches, so no random draw of PPO's changes.
    """

    extras: dict[str, np.ndarray]

    def reset(self) -> None:
        """Empties the buffer and its extras."""
        super().reset()
        self.extras = {}

    def get(  # type: ignore[override]
        self, batch_size: int | None = None
    ) -> Generator[EsaRolloutBufferSamples, None, None]:
        """SB3's minibatches, each with its extras."""
        if not self.generator_ready:
            for name, values in self.extras.items():
                self.extras[name] = self.swap_and_flatten(values)
        yield from super().get(batch_size)  # type: ignore[misc]

    def _get_samples(  # type: ignore[override]
        self, batch_inds: np.ndarray, env: VecNormalize | None = None
    ) -> EsaRolloutBufferSamples:
        base = super()._get_samples(batch_inds, env)
        extras = {name: self.to_torch(values[batch_inds]) for name, values in self.extras.items()}
        return EsaRolloutBufferSamples(*base, extras=extras)
