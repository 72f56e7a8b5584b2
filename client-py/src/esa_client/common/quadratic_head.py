"""ESAPPO's critic for ESA: a head quadratic in the policy-normalized action, and its gate.

PPO has no action-value network to probe, so ESAPPO fits one of its own:
``A(s, a) = w(s) . z + sum_j u_j(s) (z_j^2 - 1)`` with ``z = (a - mu(s)) / sigma(s)`` and
``u = -softplus(.) <= 0``, one small tanh MLP of the observation giving ``(w, u)``. It is
concave in each dimension, so ESA's filtered response follows its slope ``w_j + 2 u_j z_j``
and the shift converges to the head's maximum ``z* = -w / (2 u)``: extremum seeking, which
a head linear in the action cannot give (its response depends on neither the sample nor
the shift). ``A(s, mu) = -sum_j u_j`` keeps the head's mean over the policy 0, as an
advantage's is. It is regressed onto the normalized GAE advantages of the last few rollouts
(each stored with the ``z`` of the policy that collected it), on a generator of its own.

The gate: the rank correlation, on a rollout the head was not trained on, between its
``A(s, a) - A(s, mu)`` and the GAE advantage of the action taken (:func:`critic_quality`).

At a step the head is evaluated at the action the env executes, the action clipped to the
Box (:class:`CriticAtStep`), in closed form (:meth:`CriticAtStep.closed_form`): a
:class:`~esa_client.transports.base.QuadraticCritic`, which the in-process engine evaluates
itself.
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
    """``A(s, a) = w(s) . z + sum_j u_j(s) (z_j^2 - 1)``, ``u = -softplus(.) <= 0``.

    Args:
        features_dim: Size of the (flattened) observation features.
        action_dim: Action dimension D.
        hidden: Hidden units of each of the two layers.
    """

    def __init__(self, features_dim: int, action_dim: int, hidden: int = 64) -> None:
        """Builds the network."""
        super().__init__()
        self.action_dim = action_dim
        self.net = mlp(features_dim, hidden, 2 * action_dim)
        # The three layers, for coefficients(); a tuple is not registered as a submodule,
        # so the state_dict keeps its keys.
        self._linears = tuple(cast(nn.Linear, self.net[i]) for i in (0, 2, 4))

    def coefficients(self, features: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """``(w, u)`` at the features, each ``(batch, D)``; ``u <= 0``.

        ``self.net``'s forward pass without its five module calls: the same kernels on the
        same tensors (``nn.Linear`` is ``F.linear``, ``nn.Tanh`` is ``th.tanh``), so the same
        bits and autograd graph, at a fraction of the Python cost of a rollout step.
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

    Minibatches are drawn from ``rng``, not numpy's global generator, so that fitting the
    critic leaves the learner's own minibatch order untouched.
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
    """Rank correlation of ``A(s, a) - A(s, mu)`` with the GAE advantages of ``a``.

    ``critic`` is any critic of ``(features, z)``.
    """
    with th.no_grad():
        z = rollout.z
        predicted = critic(rollout.features, z) - critic(rollout.features, th.zeros_like(z))
    return rank_correlation(predicted.cpu().numpy(), advantages.cpu().numpy())


@dataclass
class CriticAtStep:
    """A critic of ``(features, z)`` at one step's N states, over actions in ESA units.

    ESA units are the Box scaled to [-1, 1]; ``mean`` and ``std`` are the policy's in those
    units. The critic is evaluated at the action the env executes, the action clipped to
    ``[low, high]``: beyond the box the env's Q is flat in the action, so a dimension whose
    sample lies past the bound by more than the probe's reach gives no response and its
    shift is not pushed by a slope the head extrapolated from unclipped samples.

    Attributes:
        critic: The quadratic head (or another critic of ``(features, z)``).
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
        # An op of a float32 and a float64 array widens the float32 one first, at a few times
        # the cost of an op of one dtype: widened once here, the same values. sigma^2 is
        # taken in sigma's own dtype, then widened.
        square = (self.std * self.std).astype(np.float64)
        mean, std = self.mean.astype(np.float64), self.std.astype(np.float64)
        curvature = u / square
        gain = w / std - 2.0 * curvature * mean
        offset = (curvature * mean * mean - w * mean / std - u).sum(axis=1)
        return QuadraticCritic(gain, curvature, offset, self.low, self.high)

    def gradient(self, actions: np.ndarray) -> np.ndarray:
        """``dA/dz`` at ``(N, D)`` actions in ESA units, ``(N, D)``.

        The gradient control's direction in units of sigma; 0 in a dimension past the Box,
        where the executed action does not move with the sample.
        """
        # Rollouts run under no_grad or inference_mode; autograd.grad, not backward, so that
        # the critic's own .grad does not collect this. Features made in inference mode
        # cannot be saved for the backward pass: a copy outside it can.
        with th.inference_mode(False), th.enable_grad():
            features = self.features.clone() if self.features.is_inference() else self.features
            z = th.as_tensor(self.z(actions), dtype=features.dtype).requires_grad_(True)
            (grad,) = th.autograd.grad(self.critic(features, z).sum(), z)
        inside = (actions >= self.low) & (actions <= self.high)
        result: np.ndarray = grad.cpu().numpy().astype(np.float64) * inside
        return result
