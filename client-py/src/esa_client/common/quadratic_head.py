"""ESAPPO's critic for ESA: a head quadratic in the policy-normalized action, and its gate.

PPO has no Q-network to probe, so ESAPPO fits :class:`QuadraticHead` (the SB3 guide). Being
concave in each dimension, ESA's shift converges to its maximum ``z* = -w / (2 u)``, which a
head linear in the action cannot give. ``A(s, mu) = -sum_j u_j`` keeps its mean over the
policy 0, as an advantage's is. The gate is :func:`critic_quality` on a rollout the head was
not trained on.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from typing import cast

import numpy as np
import torch as th
from torch import nn
from torch.nn import functional as F

from .. import _native
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
        # For closed_form(); a tuple is no submodule, so the state_dict keeps its keys.
        self._linears = tuple(cast(nn.Linear, self.net[i]) for i in (0, 2, 4))

    def closed_form(
        self, features: th.Tensor, mean: np.ndarray, std: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(gain, curvature, offset)`` of :meth:`forward` over ``a = mu + sigma z``.

        ``A = sum_j c_j a_j^2 + g_j a_j`` plus the offset, ``c = u / sigma^2``,
        ``g = w / sigma - 2 c mu``, at ``(N, F)`` features for the policy's ``(N, D)`` mean and
        std. esa-core's forward pass, on a copy of the weights taken when they last changed:
        torch's per-op cost on one step's states is many times the arithmetic.
        """
        # _parameters, not .weight: a module's attribute lookup costs more than the forward.
        layers = [cast(_Layer, tuple(layer._parameters.values())) for layer in self._linears]
        versions = tuple((t.data_ptr(), t._version) for layer in layers for t in layer)
        cached = _COPIES.get(self)
        if cached is None or cached[0] != versions:
            arrays = [
                (weight.detach().cpu().numpy(), bias.detach().cpu().numpy())
                for weight, bias in layers
            ]
            cached = _COPIES[self] = (versions, _native.QuadraticHead(arrays))
        return cached[1].closed_form(features.detach().cpu().numpy(), mean, std)

    def forward(self, features: th.Tensor, z: th.Tensor) -> th.Tensor:
        """A for policy-normalized actions ``z``, shape ``(batch,)``."""
        raw = self.net(features)
        dim = self.action_dim
        w, u = raw.narrow(1, 0, dim), -F.softplus(raw.narrow(1, dim, dim))
        value: th.Tensor = (w * z + u * (z * z - 1.0)).sum(dim=1)
        return value


_Layer = tuple[th.Tensor, th.Tensor]
_Versions = tuple[tuple[int, int], ...]
_COPIES: weakref.WeakKeyDictionary[QuadraticHead, tuple[_Versions, _native.QuadraticHead]] = (
    weakref.WeakKeyDictionary()
)
"""Each head's weights in esa-core, with the storage and version of each tensor they copy: not
on the module, which pickles (RLlib ships it to its env runners) and esa-core's copy does not."""


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
    if isinstance(critic, QuadraticHead):  # a fused optimizer's step bumps no tensor version
        _COPIES.pop(critic, None)
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

        With ``x = clip(a)``, :meth:`QuadraticHead.closed_form`: :meth:`__call__`'s values to
        float32 rounding.

        Raises:
            TypeError: If the critic is not a :class:`QuadraticHead`.
        """
        if not isinstance(self.critic, QuadraticHead):
            raise TypeError(f"expected a QuadraticHead, got {type(self.critic).__name__}")
        gain, curvature, offset = self.critic.closed_form(self.features, self.mean, self.std)
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
