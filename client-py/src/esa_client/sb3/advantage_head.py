"""ESAPPO's critic for ESA: an advantage head on PPO's detached value latent, and its gate.

PPO has no action-value network to probe. ``AdvantageHead`` is a small MLP
``A(latent_vf(s), a)`` regressed onto the rollout's normalized GAE advantages. It is
unit-scale whatever the reward scale, it has no state level ``V(s)`` in it (that is PPO's
value net), and its input is PPO's value latent, detached: the head does not change what
PPO learns, and costs one small MLP, not a second critic.

The gate asks whether the head knows anything about actions before ESA trusts it: the rank
correlation, on a rollout the head has not been trained on, between its
``A(s, a) - A(s, mu(s))`` and the GAE advantage of the action taken.
"""

from __future__ import annotations

import numpy as np
import torch as th
from torch import nn
from torch.nn import functional as F


class AdvantageHead(nn.Module):
    """``A(latent, a) -> R``: one tanh hidden layer, smooth in the action (ESA probes it).

    Args:
        latent_dim: Size of PPO's value latent.
        action_dim: Action dimension.
        hidden: Hidden units.
    """

    def __init__(self, latent_dim: int, action_dim: int, hidden: int = 64) -> None:
        """Builds the network."""
        super().__init__()
        self.net = nn.Sequential(
            nn.Linear(latent_dim + action_dim, hidden), nn.Tanh(), nn.Linear(hidden, 1)
        )

    def forward(self, latent: th.Tensor, actions: th.Tensor) -> th.Tensor:
        """Returns A, shape ``(batch,)``."""
        return self.net(th.cat([latent, actions], dim=1)).squeeze(1)


def normalized(advantages: th.Tensor) -> th.Tensor:
    """Advantages scaled to zero mean and unit variance, as PPO normalizes them."""
    return (advantages - advantages.mean()) / (advantages.std() + 1e-8)


def fit(
    head: AdvantageHead,
    optimizer: th.optim.Optimizer,
    latent: th.Tensor,
    actions: th.Tensor,
    advantages: th.Tensor,
    *,
    epochs: int,
    batch_size: int,
    rng: np.random.Generator,
) -> float:
    """Regresses the head onto the normalized advantages; returns the mean loss.

    Minibatches are drawn from ``rng``, not numpy's global generator, so that fitting
    the head leaves PPO's own minibatch order untouched.
    """
    target = normalized(advantages)
    n = len(target)
    losses = []
    for _ in range(epochs):
        order = th.as_tensor(rng.permutation(n))
        for idx in order.split(batch_size):
            loss = F.mse_loss(head(latent[idx], actions[idx]), target[idx])
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            losses.append(loss.item())
    return float(np.mean(losses))


def rank_correlation(x: np.ndarray, y: np.ndarray) -> float:
    """Spearman's rank correlation of two samples (0 when either is constant)."""
    rx = np.argsort(np.argsort(x)).astype(np.float64)
    ry = np.argsort(np.argsort(y)).astype(np.float64)
    rx -= rx.mean()
    ry -= ry.mean()
    denominator = np.sqrt((rx**2).sum() * (ry**2).sum())
    if denominator == 0 or np.ptp(x) == 0 or np.ptp(y) == 0:
        return 0.0
    return float((rx * ry).sum() / denominator)


def critic_quality(
    head: AdvantageHead,
    latent: th.Tensor,
    actions: th.Tensor,
    means: th.Tensor,
    advantages: th.Tensor,
) -> float:
    """Rank correlation of ``A(s, a) - A(s, mu)`` with the GAE advantages of ``a``."""
    with th.no_grad():
        predicted = head(latent, actions) - head(latent, means)
    return rank_correlation(predicted.cpu().numpy(), advantages.cpu().numpy())
