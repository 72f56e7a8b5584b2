"""ESA's step on a quadratic head, shared by ESAPPO and RLlib's PPO: the same bits."""

from __future__ import annotations

import numpy as np
import torch as th
from torch import nn

from ..transports.base import SMALLEST_SCALE
from ..transports.messages import LinearCritic, QuadraticCritic
from .action_frame import ActionFrame
from .quadratic_head import CriticAtStep
from .runtime import EsaRuntime, QFunction


def head_critic(
    head: nn.Module, features: th.Tensor, frame: ActionFrame, mean: np.ndarray, std: np.ndarray
) -> CriticAtStep:
    """The head at one step's N states (``features``, ``(N, F)``) over actions in ESA units.

    ``mean`` and ``std`` are the policy's, in action units, ``(N, D)``. The critic's ``std``
    is sigma in ESA units, floored at the smallest float32 (the contract needs sigma > 0).
    """
    units = np.maximum(std / frame.half_width, SMALLEST_SCALE)
    mean_units = (mean - frame.center) / frame.half_width
    return CriticAtStep(head, features, mean_units, units, frame.low, frame.high)


def head_shift(
    runtime: EsaRuntime,
    critic: QFunction | LinearCritic | QuadraticCritic,
    units: np.ndarray,
    frame: ActionFrame,
    sample: np.ndarray,
    starts: np.ndarray,
    strength: float,
) -> np.ndarray:
    """ESA's shift ``v(t)`` of the samples at strength ``f``, in action units, float64 ``(N, D)``.

    Args:
        runtime: The sessions, one per env.
        critic: What the sessions evaluate at the probes: :func:`head_critic`'s critic's
            ``closed_form()``, or any critic over actions in ESA units.
        units: Sigma in ESA units (the ``std`` of :func:`head_critic`'s critic).
        frame: The action space as ESA sees it.
        sample: The policy's samples ``a_t`` in action units, ``(N, D)``.
        starts: True where an env starts an episode, ``(N,)``.
        strength: ESA's strength ``f`` under the fade.
    """
    scaled = (sample - frame.center) / frame.half_width
    applied = runtime.step(scaled, starts, critic, units, strength=strength)
    shift: np.ndarray = (applied - scaled) * frame.half_width
    return shift


def shifted(sample: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """``a_t + v(t)`` in the sample's dtype, summed in float64: what the env gets (clipped)."""
    summed: np.ndarray = (sample.astype(np.float64) + shift).astype(sample.dtype)
    return summed
