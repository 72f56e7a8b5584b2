"""ESAPPO's critic for ESA: a head quadratic in the policy-normalized action, and its gate.

PPO has no Q-network to probe, so ESAPPO fits :class:`QuadraticHead` (the SB3 guide). Being
concave in each dimension, ESA's shift converges to its maximum ``z* = -w / (2 u)``, which a
head linear in the action cannot give. ``A(s, mu) = -sum_j u_j`` keeps its mean over the
policy 0, as an advantage's is. The gate is :func:`critic_quality` on a rollout the head was
not trained on.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import numpy as np
import torch as th
from torch import nn
from torch.nn import functional as F

from ..transports.base import QuadraticCritic


def mlp(inputs: int, hidden: int, outputs: int) -> nn.Sequential:
    """Two tanh layers of ``hidden`` units and a linear output."""
    return nn.Sequential(
        nn.Linear(inputs, hidden),
        nn.Tanh(),
        nn.Linear(hidden, hidden),
        nn.Tanh(),
        nn.Linear(hidden, outputs),
    )


class QuadraticHead(nn.Module):
    """``A(s, a) = w(s) . z + sum_j u_j(s) (z_j^2 - 1)``, ``u = -softplus(.) <= 0``."""

    def __init__(self, features_dim: int, action_dim: int, hidden: int = 64) -> None:
        """Builds the network: two tanh layers of ``hidden`` units, then ``(w, u)``."""
        super().__init__()
        self.action_dim = action_dim
        self.net = mlp(features_dim, hidden, 2 * action_dim)
        # For coefficients(); a tuple is no submodule, so the state_dict keeps its keys.
        self._linears = tuple(cast(nn.Linear, self.net[i]) for i in (0, 2, 4))

    def coefficients(self, features: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """``(w, u)`` at the features, each ``(batch, D)``; ``u <= 0``.

        ``self.net``'s forward pass without its module calls: the same kernels, so the same
        bits and autograd graph, at a fraction of the Python cost.
        """
        first, second, third = self._linears
        hidden = th.tanh(F.linear(features, first.weight, first.bias))
        hidden = th.tanh(F.linear(hidden, second.weight, second.bias))
        raw = F.linear(hidden, third.weight, third.bias)
        # narrow is the slice that indexing makes, without indexing's parsing of its key.
        dim = self.action_dim
        return raw.narrow(1, 0, dim), -F.softplus(raw.narrow(1, dim, dim))

    def forward(self, features: th.Tensor, z: th.Tensor) -> th.Tensor:
        """A for policy-normalized actions ``z``, shape ``(batch,)``."""
        w, u = self.coefficients(features)
        value: th.Tensor = (w * z + u * (z * z - 1.0)).sum(dim=1)
        return value


@dataclass
class Rollout:
    """What the head learns from one rollout: features, z, normalized advantages."""

    features: th.Tensor
    z: th.Tensor
    target: th.Tensor


def normalized(advantages: th.Tensor) -> th.Tensor:
    """Advantages scaled to zero mean and unit variance, as PPO normalizes them."""
    return (advantages - advantages.mean()) / (advantages.std() + 1e-8)


def fit_critic(
    critic: nn.Module,
    optimizer: th.optim.Optimizer,
    rollouts: list[Rollout],
    *,
    epochs: int,
    batch_size: int,
    rng: np.random.Generator,
) -> float:
    """Regresses ``critic(features, z)`` onto the rollouts' targets; returns the mean loss.

    Minibatches come from ``rng``, so the learner's own minibatch order is untouched.
    """
    features = th.cat([r.features for r in rollouts])
    z = th.cat([r.z for r in rollouts])
    target = th.cat([r.target for r in rollouts])
    losses = []
    for _ in range(epochs):
        order = th.as_tensor(rng.permutation(len(target)))
        for idx in order.split(batch_size):
            loss = F.mse_loss(critic(features[idx], z[idx]), target[idx])
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            losses.append(loss.detach())
    return float(th.stack(losses).mean())


def rank_correlation(x: np.ndarray, y: np.ndarray) -> float:
    """Spearman's rank correlation of two samples (0 when either is constant)."""
    if np.ptp(x) == 0 or np.ptp(y) == 0:
        return 0.0
    rx = np.argsort(np.argsort(x)).astype(np.float64)
    ry = np.argsort(np.argsort(y)).astype(np.float64)
    rx -= rx.mean()
    ry -= ry.mean()
    return float((rx * ry).sum() / np.sqrt((rx**2).sum() * (ry**2).sum()))


def critic_quality(critic: nn.Module, rollout: Rollout, advantages: th.Tensor) -> float:
    """Rank correlation of ``critic``'s ``A(s, a) - A(s, mu)`` with the GAE advantages of ``a``."""
    with th.no_grad():
        z = rollout.z
        predicted = critic(rollout.features, z) - critic(rollout.features, th.zeros_like(z))
    return rank_correlation(predicted.cpu().numpy(), advantages.cpu().numpy())


@dataclass
class CriticAtStep:
    """A critic of ``(features, z)`` at one step's N states, over actions in ESA units.

    ``features`` is ``(N, F)``; the policy's ``mean`` and ``std`` are ``(N, D)`` and the Box's
    ``low`` and ``high`` ``(D,)`` (+-inf where open), all in ESA units. It is evaluated at the
    action the env executes, clipped to ``[low, high]``: past the box the env's Q is flat,
    so no slope extrapolated from unclipped samples pushes the shift.
    """

    critic: nn.Module
    features: th.Tensor
    mean: np.ndarray
    std: np.ndarray
    low: np.ndarray
    high: np.ndarray

    def z(self, actions: np.ndarray) -> np.ndarray:
        """``(clip(a) - mu) / sigma`` for ``(k N, D)`` actions at the N states tiled k times."""
        reps = len(actions) // len(self.mean)
        clipped = np.clip(actions, self.low, self.high)
        z: np.ndarray = (clipped - np.tile(self.mean, (reps, 1))) / np.tile(self.std, (reps, 1))
        return z

    def __call__(self, actions: np.ndarray) -> np.ndarray:
        """The critic at ``(k N, D)`` actions in ESA units, shape ``(k N,)``."""
        z = self.z(actions)
        reps = len(z) // len(self.mean)
        features = self.features.repeat(reps, 1)
        with th.no_grad():
            values = self.critic(features, th.as_tensor(z, dtype=features.dtype))
        result: np.ndarray = values.cpu().numpy().astype(np.float64)
        return result

    def closed_form(self) -> QuadraticCritic:
        """The quadratic head at the N states as a critic over actions in ESA units.

        With ``x = clip(a)``, ``A`` is ``sum_j c_j x_j^2 + g_j x_j`` plus an offset,
        ``c = u / sigma^2 <= 0``, ``g = w / sigma - 2 c mu``: :meth:`__call__`'s values to
        float32 rounding.

        Raises:
            TypeError: If the critic is not a :class:`QuadraticHead`.
        """
        if not isinstance(self.critic, QuadraticHead):
            raise TypeError(f"expected a QuadraticHead, got {type(self.critic).__name__}")
        with th.no_grad():
            w_t, u_t = self.critic.coefficients(self.features)
        w = w_t.cpu().numpy().astype(np.float64)
        u = u_t.cpu().numpy().astype(np.float64)
        # Widened once here rather than in each mixed-dtype op (the same values); sigma^2 is
        # taken in sigma's own dtype, then widened.
        square = (self.std * self.std).astype(np.float64)
        mean, std = self.mean.astype(np.float64), self.std.astype(np.float64)
        curvature = u / square
        gain = w / std - 2.0 * curvature * mean
        offset = (curvature * mean * mean - w * mean / std - u).sum(axis=1)
        return QuadraticCritic(gain, curvature, offset, self.low, self.high)

    def gradient(self, actions: np.ndarray) -> np.ndarray:
        """``dA/dz`` at ``(N, D)`` actions in ESA units; 0 in a dimension past the Box."""
        # autograd.grad, not backward: the critic's own .grad must not collect this.
        # Features made in inference mode cannot be saved for backward: a copy can.
        with th.inference_mode(False), th.enable_grad():
            features = self.features.clone() if self.features.is_inference() else self.features
            z = th.as_tensor(self.z(actions), dtype=features.dtype).requires_grad_(True)
            (grad,) = th.autograd.grad(self.critic(features, z).sum(), z)
        inside = (actions >= self.low) & (actions <= self.high)
        result: np.ndarray = grad.cpu().numpy().astype(np.float64) * inside
        return result
