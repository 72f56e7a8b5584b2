"""The first ESAPPO's critic: an advantage head linear in the policy-normalized action.

``A(s, a) = w(s) . z`` with ``z = (a - mu(s)) / sigma(s)``, ``w`` a small tanh MLP of the
observation, regressed onto normalized GAE advantages of the last few rollouts: the policy
gradient's own form (compatible features of a Gaussian policy). It has no extremum in the
action: probed with the paired response, ESA's filtered signal depends on neither the sample
nor the shift, so the shift integrates ``w(s)`` open-loop up to its trust region. That is
why the product moved to the quadratic head (E1 and E2 of ``RESULTS.md``); the confirmation
campaign and E1 ran this one, so it stays here for them.

Per rollout step, :meth:`AdvantageHead.snapshot` gives ``w(s)`` and the step's linear
critic (:class:`HeadSnapshot`: numpy, each operation in a fixed precision and order, so that
a re-run keeps its bits); its fit writes the backward pass out (:func:`fit`).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
from collections.abc import Callable, Sequence
from typing import Any, cast

import numpy as np
import torch as th
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

    def snapshot(self, center: np.ndarray, half_width: np.ndarray) -> HeadSnapshot:
        """The network as it is now, for one rollout step at a time.

        Args:
            center: The action Box's center, per dimension (0 where a side is open).
            half_width: Its half-width (1 where a side is open): ESA units are
                ``(a - center) / half_width``.

        Returns:
            A :class:`HeadSnapshot` that gives ``w(s)`` and the step's critic in ESA units.
            Its float32 arithmetic rounds differently from torch's kernels: ``w`` agrees
            with :meth:`weights` to float32 precision, not bit for bit.
        """
        return HeadSnapshot(
            [layer.weight.detach().cpu().numpy() for layer in self._linears],
            [layer.bias.detach().cpu().numpy() for layer in self._linears],
            [float(c) for c in center],
            [float(h) for h in half_width],
            # numpy divides the policy's float32 std by a float32 (or float16) half-width in
            # float32: the snapshot's std in ESA units keeps those bits.
            single_units=np.result_type(np.float32, np.asarray(half_width)) == np.float32,
        )

    def version(self) -> tuple[int, ...]:
        """Changes whenever the parameters change: a :func:`fit`, a load, an in-place write."""
        return (self.fits, *(p._version for p in self._parameters_held))


class HeadSnapshot:
    """The head's layers and the action Box's scaling, for one rollout step at a time.

    Gives ``w(s)`` and the step's critic linear in the action in ESA units,
    ``Q(x) = gain . x + offset`` with ``gain = w h / sigma`` and
    ``offset = w . (c - mu) / sigma`` (``c``, ``h``: the Box's center and half-width), which
    the engine's closed form steps. Every float32 and float64 operation runs in a fixed
    order, so a run's bits depend on neither torch's nor BLAS's kernels.

    Args:
        weights: Each layer's weight, float32 ``(outputs, inputs)`` as torch stores it; tanh
            between layers, none after the last.
        biases: Each layer's bias, float32 ``(outputs,)``.
        center: The Box's center per action dimension.
        half_width: Its half-width per dimension, > 0.
        single_units: Divide the std by the half-width in float32 (a float32 or float16
            Box, as numpy divides the policy's float32 std there), else in float64.

    Raises:
        ValueError: If the shapes do not chain, or the scaling is not finite and positive.
    """

    def __init__(
        self,
        weights: Sequence[np.ndarray],
        biases: Sequence[np.ndarray],
        center: Sequence[float],
        half_width: Sequence[float],
        single_units: bool = False,
    ) -> None:
        """Copies the layers and checks that they chain."""
        if not weights or len(weights) != len(biases):
            raise ValueError(
                "expected as many biases as weights (at least one layer), "
                f"got {len(weights)} and {len(biases)}"
            )
        self._layers: list[tuple[np.ndarray, np.ndarray]] = []
        for index, (weight, bias) in enumerate(zip(weights, biases, strict=True)):
            weight = np.array(weight, dtype=np.float32)
            bias = np.array(bias, dtype=np.float32)
            inputs = self._layers[-1][1].size if self._layers else weight.shape[-1]
            if weight.ndim != 2 or weight.shape[1] != inputs or bias.shape != weight.shape[:1]:
                raise ValueError(
                    f"layer {index}: expected a weight of shape (outputs, {inputs}) and a bias "
                    f"of length outputs, got {weight.shape} and {bias.shape}"
                )
            self._layers.append((weight, bias))
        self.features_dim = self._layers[0][0].shape[1]
        self.action_dim = self._layers[-1][1].size
        self._center = np.array(center, dtype=np.float64)
        self._half_width = np.array(half_width, dtype=np.float64)
        if self._center.shape != (self.action_dim,) or self._half_width.shape != (self.action_dim,):
            raise ValueError(
                f"expected center and half_width of length {self.action_dim} (the last "
                f"layer's outputs), got {self._center.shape} and {self._half_width.shape}"
            )
        if (
            not (np.isfinite(self._center).all() and np.isfinite(self._half_width).all())
            or (self._half_width <= 0).any()
        ):
            raise ValueError(
                f"expected finite center and half_width > 0, got {center} and {half_width}"
            )
        self._single_units = single_units

    def weights(self, features: np.ndarray) -> np.ndarray:
        """``w(features)``: float64 ``(N, D)`` of ``(N, F)`` features.

        Float64 features are rounded to float32 first (to nearest, ties to even), as
        torch's ``float()`` rounds them.
        """
        return self._w(features).astype(np.float64)

    def critic(
        self, features: np.ndarray, mean: np.ndarray, std: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(gain, offset)`` of ``A = w . (a - mean) / std`` for ``a = c + h x``.

        ``gain = w h / std`` and ``offset = w . (c - mean) / std``: float64 ``(N, D)`` and
        ``(N,)`` from the policy's float32 ``(N, D)`` ``mean`` and ``std``.

        Raises:
            ValueError: If a shape does not match the head's (F, D) or the row count.
        """
        return self._linear_critic(self._w(features), mean, std)

    def step_inputs(
        self, features: np.ndarray, actions: np.ndarray, mean: np.ndarray, std: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The step's inputs: ``(scaled, gain, offset, units)``, float64.

        ``scaled`` is the policy's float32 sample ``actions`` in ESA units,
        ``(a - c) / h``; ``(gain, offset)`` is :meth:`critic`; ``units`` is the std in ESA
        units, ``max(std / h, tiny)`` with float32's smallest normal ``tiny`` (the
        contract needs sigma > 0), divided in float32 for a float32 Box.

        Raises:
            ValueError: If a shape does not match the head's (F, D) or the row count.
        """
        w = self._w(features)
        actions = _matrix(actions, self.action_dim, "actions")
        if len(actions) != len(w):
            raise ValueError(
                f"expected actions with {len(w)} rows (one per features row), got {len(actions)}"
            )
        gain, offset = self._linear_critic(w, mean, std)
        scaled = (actions.astype(np.float64) - self._center) / self._half_width
        return scaled, gain, offset, self._units(std)

    def shift(self, scaled: np.ndarray, applied: np.ndarray) -> np.ndarray:
        """The shift of the step's answer in the Box's units: ``(applied - scaled) h``.

        Raises:
            ValueError: If ``scaled`` and ``applied`` are not both ``(N, D)``.
        """
        scaled = _matrix(scaled, self.action_dim, "scaled", np.float64)
        applied = _matrix(applied, self.action_dim, "applied", np.float64)
        if len(scaled) != len(applied):
            raise ValueError(
                "expected scaled and applied with as many rows, "
                f"got {len(scaled)} and {len(applied)}"
            )
        shift: np.ndarray = (applied - scaled) * self._half_width
        return shift

    def _w(self, features: np.ndarray) -> np.ndarray:
        """``w(features)`` in float32, each sum over a layer's inputs taken in order."""
        hidden = _matrix(features, self.features_dim, "features", np.float32)
        last = len(self._layers) - 1
        for index, (weight, bias) in enumerate(self._layers):
            # A sequential sum, then the bias: np.add.accumulate adds in order where a
            # matrix product's kernels regroup the sum (and so round differently).
            products = hidden[:, None, :] * weight
            hidden = np.add.accumulate(products, axis=2)[:, :, -1] + bias
            if index < last:
                hidden = _tanhf(hidden)
        return hidden

    def _linear_critic(
        self, w: np.ndarray, mean: np.ndarray, std: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The critic of :meth:`critic` from ``w``, checking ``mean`` and ``std``."""
        mean = _matrix(mean, self.action_dim, "mean")
        std = _matrix(std, self.action_dim, "std")
        if len(mean) != len(w) or len(std) != len(w):
            raise ValueError(
                f"expected mean and std with {len(w)} rows (one per features row), "
                f"got {len(mean)} and {len(std)}"
            )
        w, sigma = w.astype(np.float64), std.astype(np.float64)
        # IEEE's infinities and NaN for a zero std, without a warning per step.
        with np.errstate(divide="ignore", invalid="ignore"):
            gain = w * self._half_width / sigma
            terms = w * (self._center - mean.astype(np.float64)) / sigma
            # Summed dimension by dimension from 0.0, not by numpy's pairwise reduction.
            offset = np.zeros(len(w))
            for term in terms.T:
                offset += term
        return gain, offset

    def _units(self, std: np.ndarray) -> np.ndarray:
        """``max(std / h, tiny)`` (NaN kept), float64, in float32 for a float32 Box."""
        std = _matrix(std, self.action_dim, "std")
        tiny = np.finfo(np.float32).tiny
        with np.errstate(over="ignore", invalid="ignore"):
            if self._single_units:
                # Exact: the half-width is a float32 widened.
                unit = std / self._half_width.astype(np.float32)
            else:
                unit = std.astype(np.float64) / self._half_width
        floored: np.ndarray = np.where(unit < tiny, unit.dtype.type(tiny), unit)
        return floored.astype(np.float64)


def _matrix(
    array: np.ndarray, width: int, name: str, dtype: type[np.floating[Any]] = np.float32
) -> np.ndarray:
    """``array`` as ``dtype`` ``(N, width)``, or a ``ValueError`` naming it."""
    matrix = np.asarray(array, dtype=dtype)
    if matrix.ndim != 2 or matrix.shape[1] != width:
        raise ValueError(f"{name}: expected {width} columns, got shape {matrix.shape}")
    return matrix


@functools.cache
def _c_tanhf() -> Callable[[float], float]:
    """The C library's ``tanhf``.

    numpy's and torch's float32 tanh are vector kernels of their own, which round some
    values differently; the lab's runs took the C library's.
    """
    tanhf = ctypes.CDLL(ctypes.util.find_library("m")).tanhf
    tanhf.restype = ctypes.c_float
    tanhf.argtypes = (ctypes.c_float,)
    return cast(Callable[[float], float], tanhf)


def _tanhf(values: np.ndarray) -> np.ndarray:
    """The C library's tanh of each float32 value (exact through Python's floats)."""
    flat = values.ravel().tolist()
    return np.fromiter(map(_c_tanhf(), flat), np.float32, len(flat)).reshape(values.shape)


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
