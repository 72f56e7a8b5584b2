"""The first ESAPPO's critic: an advantage head linear in the policy-normalized action.

``A(s, a) = w(s) . z`` with ``z = (a - mu(s)) / sigma(s)``, ``w`` a small tanh MLP of the
observation, regressed onto normalized GAE advantages of the last few rollouts: the policy
gradient's own form (compatible features of a Gaussian policy). It has no extremum in the
action: probed with the paired response, ESA's filtered signal depends on neither the sample
nor the shift, so the shift integrates ``w(s)`` open-loop up to its trust region. That is
why the product moved to the quadratic head (E1 and E2 of ``RESULTS.md``); the confirmation
campaign and E1 ran this one, so it stays here for them.

Its Rust copy (:class:`esa_client._native.AdvantageMlp`, :meth:`AdvantageHead.snapshot`)
gives ``w(s)`` and the step's linear critic per rollout step without torch's per-call cost;
its fit writes the backward pass out (:func:`fit`). Both keep the bits the committed runs
were made with.
"""

from __future__ import annotations

from typing import cast

import numpy as np
import torch as th
from esa_client._native import AdvantageMlp
from esa_client.common.quadratic_head import Rollout
from torch import nn
from torch.nn import functional as F


class AdvantageHead(nn.Module):
    """``A(s, a) = w(s) . (a - mu) / sigma``, ``w`` a tanh MLP of the observation features.

    Args:
        features_dim: Size of the (flattened) observation features.
        action_dim: Action dimension.
        hidden: Hidden units of each of the two layers.
    """

    def __init__(self, features_dim: int, action_dim: int, hidden: int = 64) -> None:
        """Builds the network."""
        super().__init__()
        self.w = nn.Sequential(
            nn.Linear(features_dim, hidden),
            nn.Tanh(),
            nn.Linear(hidden, hidden),
            nn.Tanh(),
            nn.Linear(hidden, action_dim),
        )
        # The three layers, for weights(): indexing a Sequential costs microseconds. A
        # tuple is not registered as a submodule, so the state_dict keeps its keys.
        self._linears = tuple(cast(nn.Linear, self.w[i]) for i in (0, 2, 4))
        # Weight and bias of each layer, in order: for version() (parameters() walks the
        # modules on every call) and for fit()'s written-out gradients.
        self._parameters_held = tuple(
            t for layer in self._linears for t in (layer.weight, layer.bias)
        )
        # Counted by fit(): a fused optimizer writes the parameters without bumping their
        # version counters.
        self.fits = 0

    def forward(self, features: th.Tensor, z: th.Tensor) -> th.Tensor:
        """Returns A for policy-normalized actions ``z``, shape ``(batch,)``."""
        return self.advantage(self.weights(features), z)

    def weights(self, features: th.Tensor) -> th.Tensor:
        """``w(features)``: ``self.w``'s forward pass without its six module calls.

        The same kernels on the same tensors as ``self.w(features)`` (``nn.Linear`` is
        ``F.linear``, ``nn.Tanh`` is ``th.tanh``), so the same bits and the same autograd
        graph; the module calls' Python overhead was a third of the per-step cost of the
        head.
        """
        first, second, third = self._linears
        hidden = th.tanh(F.linear(features, first.weight, first.bias))
        hidden = th.tanh(F.linear(hidden, second.weight, second.bias))
        return F.linear(hidden, third.weight, third.bias)

    @staticmethod
    def advantage(w: th.Tensor, z: th.Tensor) -> th.Tensor:
        """``A = w . z`` row by row, from the network's output ``w = self.w(features)``."""
        value: th.Tensor = (w * z).sum(dim=1)
        return value

    def snapshot(self, center: np.ndarray, half_width: np.ndarray) -> AdvantageMlp:
        """The network as it is now, in Rust, for one rollout step at a time.

        Args:
            center: The action Box's center, per dimension (0 where a side is open).
            half_width: Its half-width (1 where a side is open): ESA units are
                ``(a - center) / half_width``.

        Returns:
            An :class:`esa_client._native.AdvantageMlp` that gives ``w(s)`` and the step's
            critic in ESA units. Its float32 arithmetic rounds differently from torch's
            kernels: ``w`` agrees with :meth:`weights` to float32 precision, not bit for bit.
        """
        return AdvantageMlp(
            [layer.weight.detach().cpu().numpy() for layer in self._linears],
            [layer.bias.detach().cpu().numpy() for layer in self._linears],
            [float(c) for c in center],
            [float(h) for h in half_width],
            # numpy divides the policy's float32 std by a float32 (or float16) half-width in
            # float32: the Rust copy's std in ESA units keeps those bits.
            single_units=np.result_type(np.float32, np.asarray(half_width)) == np.float32,
        )

    def version(self) -> tuple[int, ...]:
        """Changes whenever the parameters change: a :func:`fit`, a load, an in-place write."""
        return (self.fits, *(p._version for p in self._parameters_held))


def fit(
    head: AdvantageHead,
    optimizer: th.optim.Optimizer,
    rollouts: list[Rollout],
    *,
    epochs: int,
    batch_size: int,
    rng: np.random.Generator,
) -> float:
    """Regresses the head onto the rollouts' normalized advantages; returns the mean loss.

    The loss of a minibatch is the mean squared error of ``A = w(s) . z``; its gradients
    come from :func:`_gradients`, the backward pass written out. Minibatches are drawn
    from ``rng``, not numpy's global generator, so that fitting the head leaves PPO's own
    minibatch order untouched.
    """
    features = th.cat([r.features for r in rollouts])
    z = th.cat([r.z for r in rollouts])
    target = th.cat([r.target for r in rollouts])
    losses = []
    with th.no_grad():
        for _ in range(epochs):
            order = th.as_tensor(rng.permutation(len(target)))
            for idx in order.split(batch_size):
                loss, gradients = _gradients(head, features[idx], z[idx], target[idx])
                for parameter, gradient in zip(head._parameters_held, gradients, strict=True):
                    parameter.grad = gradient
                optimizer.step()
                losses.append(loss)
    head.fits += 1
    return float(th.stack(losses).mean())


def _gradients(
    head: AdvantageHead, features: th.Tensor, z: th.Tensor, target: th.Tensor
) -> tuple[th.Tensor, list[th.Tensor]]:
    """The minibatch's mean squared error and its gradients (weight, bias per layer).

    :meth:`AdvantageHead.weights`'s backward pass written out: for this small net, autograd's
    graph bookkeeping cost a third of the fit; the same
    products in the same float32, equal to autograd's gradients up to rounding.
    """
    first, second, third = head._linears
    hidden1 = th.tanh(th.addmm(first.bias, features, first.weight.t()))
    hidden2 = th.tanh(th.addmm(second.bias, hidden1, second.weight.t()))
    w = th.addmm(third.bias, hidden2, third.weight.t())
    residual = (w * z).sum(dim=1) - target
    grad_w = z * (residual * (2.0 / len(target))).unsqueeze(1)
    grad2 = (grad_w @ third.weight) * (1 - hidden2 * hidden2)
    grad1 = (grad2 @ second.weight) * (1 - hidden1 * hidden1)
    gradients = [
        grad1.t() @ features,
        grad1.sum(dim=0),
        grad2.t() @ hidden1,
        grad2.sum(dim=0),
        grad_w.t() @ hidden2,
        grad_w.sum(dim=0),
    ]
    return residual.square().mean(), gradients
