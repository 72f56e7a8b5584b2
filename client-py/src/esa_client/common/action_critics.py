"""ESAPPO's critics with curvature in the action: a quadratic advantage head and a Q-network.

The linear head of :mod:`esa_client.common.advantage_head`, ``A = w(s) . z``, has no
extremum: probed with the paired response, its filtered signal depends on neither the
sample nor the shift, so ESA integrates ``w(s)`` open-loop up to its bound
(``shared/research/esa-seeks.md`` section 1). The critics here restore the loop:

* :class:`QuadraticHead`: ``A = w(s) . z + sum_j u_j(s) (z_j^2 - 1)`` with ``u_j <= 0``
  (``u = -softplus(.)``), ``z = (a - mu) / sigma``. Concave in each dimension, so ESA's
  shift follows ``w_j + 2 u_j z_j`` and converges to the head's maximum
  ``z* = -w / (2 u)``. ``A(s, mu) = -sum_j u_j`` keeps the head's mean over the policy 0,
  as an advantage's is. Evaluated in closed form.
* :class:`QNetwork`: ``Q(s, z)`` a tanh MLP of the observation features and ``z``, the
  paper's choice (Algorithm 1 probes a learned action-value network): any shape in the
  action, at the cost of a network forward pass per probe.

Both are regressed, like the linear head, onto the normalized GAE advantages of the last
few rollouts (:class:`~esa_client.common.advantage_head.Rollout`), with autograd and Adam.
Both are evaluated at the action the env executes: the action clipped to the Box (see
:class:`CriticAtStep`); the quadratic head's closed form there is a
:class:`~esa_client.transports.base.QuadraticCritic` (:meth:`CriticAtStep.closed_form`),
which the in-process engine evaluates itself.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch as th
from torch import nn
from torch.nn import functional as F

from ..transports.base import QuadraticCritic
from .advantage_head import Rollout

CriticKind = Literal["linear", "quadratic", "qnet"]
"""ESAPPO's critic: the linear advantage head, the quadratic head, or a Q-network."""
CRITIC_KINDS: tuple[CriticKind, ...] = ("linear", "quadratic", "qnet")


def _mlp(inputs: int, hidden: int, outputs: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Linear(inputs, hidden),
        nn.Tanh(),
        nn.Linear(hidden, hidden),
        nn.Tanh(),
        nn.Linear(hidden, outputs),
    )


class QuadraticHead(nn.Module):
    """``A(s, a) = w(s) . z + sum_j u_j(s) (z_j^2 - 1)``, ``u = -softplus(.) <= 0``.

    One tanh MLP of the observation features gives ``(w, u)`` (2 D outputs).

    Args:
        features_dim: Size of the (flattened) observation features.
        action_dim: Action dimension D.
        hidden: Hidden units of each of the two layers.
    """

    def __init__(self, features_dim: int, action_dim: int, hidden: int = 64) -> None:
        """Builds the network."""
        super().__init__()
        self.action_dim = action_dim
        self.net = _mlp(features_dim, hidden, 2 * action_dim)

    def coefficients(self, features: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """``(w, u)`` at the features, each ``(batch, D)``; ``u <= 0``."""
        raw = self.net(features)
        return raw[:, : self.action_dim], -F.softplus(raw[:, self.action_dim :])

    def forward(self, features: th.Tensor, z: th.Tensor) -> th.Tensor:
        """A for policy-normalized actions ``z``, shape ``(batch,)``."""
        w, u = self.coefficients(features)
        value: th.Tensor = (w * z + u * (z * z - 1.0)).sum(dim=1)
        return value


class QNetwork(nn.Module):
    """``Q(s, z)``: a tanh MLP of the observation features and ``z = (a - mu) / sigma``.

    Args:
        features_dim: Size of the (flattened) observation features.
        action_dim: Action dimension D.
        hidden: Hidden units of each of the two layers.
    """

    def __init__(self, features_dim: int, action_dim: int, hidden: int = 64) -> None:
        """Builds the network."""
        super().__init__()
        self.net = _mlp(features_dim + action_dim, hidden, 1)

    def forward(self, features: th.Tensor, z: th.Tensor) -> th.Tensor:
        """Q for policy-normalized actions ``z``, shape ``(batch,)``."""
        value: th.Tensor = self.net(th.cat([features, z], dim=1)).squeeze(1)
        return value


def make_critic(kind: CriticKind, features_dim: int, action_dim: int, hidden: int) -> nn.Module:
    """A fresh quadratic head or Q-network (the linear head is ``AdvantageHead``)."""
    if kind == "quadratic":
        return QuadraticHead(features_dim, action_dim, hidden)
    if kind == "qnet":
        return QNetwork(features_dim, action_dim, hidden)
    raise ValueError(f"expected a critic kind in ('quadratic', 'qnet'), got {kind!r}")


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

    Minibatches are drawn from ``rng`` (the learner's own numpy and torch streams stay
    untouched), as :func:`~esa_client.common.advantage_head.fit` does for the linear head.
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


@dataclass
class CriticAtStep:
    """A curved critic at one step's N states, as ESA's critic over actions in ESA units.

    ESA units are the Box scaled to [-1, 1]; ``mean`` and ``std`` are the policy's in those
    units. The critic is evaluated at the action the env executes, the action clipped to
    ``[low, high]``: beyond the box the env's Q is flat in the action, so a dimension whose
    sample lies past the bound by more than the probe's reach gives no response and its
    shift is not pushed by a slope the head extrapolated from unclipped samples.

    Attributes:
        critic: The quadratic head or Q-network.
        features: Its input at the N states, ``(N, F)``.
        mean: The policy's mean in ESA units, ``(N, D)``.
        std: The policy's std in ESA units, ``(N, D)``.
        low: The Box's lower bounds in ESA units, ``(D,)`` (-inf where open).
        high: Its upper bounds, ``(D,)``.
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

        With ``(w, u)`` the head's coefficients (one forward pass) and ``x = clip(a)``,
        ``A = sum_j w_j z_j + u_j (z_j^2 - 1)``, ``z = (x - mu) / sigma``, is
        ``sum_j c_j x_j^2 + g_j x_j`` plus an offset, with ``c = u / sigma^2 <= 0`` and
        ``g = w / sigma - 2 c mu``: :meth:`__call__`'s values to float32 rounding (the head
        runs in float32, this in float64).

        Raises:
            TypeError: If the critic is not a :class:`QuadraticHead`.
        """
        if not isinstance(self.critic, QuadraticHead):
            raise TypeError(f"expected a QuadraticHead, got {type(self.critic).__name__}")
        with th.no_grad():
            w_t, u_t = self.critic.coefficients(self.features)
        w = w_t.cpu().numpy().astype(np.float64)
        u = u_t.cpu().numpy().astype(np.float64)
        curvature = u / (self.std * self.std)
        gain = w / self.std - 2.0 * curvature * self.mean
        offset = (curvature * self.mean * self.mean - w * self.mean / self.std - u).sum(axis=1)
        return QuadraticCritic(gain, curvature, offset, self.low, self.high)

    def gradient(self, actions: np.ndarray) -> np.ndarray:
        """``dA/dz`` at ``(N, D)`` actions in ESA units, ``(N, D)``.

        The gradient control's direction in units of sigma; 0 in a dimension past the Box,
        where the executed action does not move with the sample.
        """
        # Rollouts run under no_grad; autograd.grad, not backward, so that the critic's own
        # .grad does not collect this.
        with th.enable_grad():
            z = th.as_tensor(self.z(actions), dtype=self.features.dtype).requires_grad_(True)
            (grad,) = th.autograd.grad(self.critic(self.features, z).sum(), z)
        inside = (actions >= self.low) & (actions <= self.high)
        result: np.ndarray = grad.cpu().numpy().astype(np.float64) * inside
        return result
