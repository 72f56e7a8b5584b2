"""The auxiliary action-value critic Q(s, a) that gives ESAPPO something to probe."""

from __future__ import annotations

from collections.abc import Sequence

import torch as th
from stable_baselines3.common.torch_layers import create_mlp
from torch import nn


class ActionCritic(nn.Module):
    """An MLP ``Q(features(s), a) -> R`` on top of the policy's (detached) value features.

    Args:
        features_dim: Size of the policy's value-function features.
        action_dim: Action dimension.
        net_arch: Hidden layer sizes.
    """

    def __init__(self, features_dim: int, action_dim: int, net_arch: Sequence[int]) -> None:
        """Builds the network."""
        super().__init__()
        self.q = nn.Sequential(*create_mlp(features_dim + action_dim, 1, list(net_arch), nn.Tanh))

    def forward(self, features: th.Tensor, actions: th.Tensor) -> th.Tensor:
        """Returns Q, shape ``(batch,)``."""
        return self.q(th.cat([features, actions], dim=1)).squeeze(1)
