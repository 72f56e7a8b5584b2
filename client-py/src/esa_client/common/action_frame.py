"""``ActionFrame``: the units ESA shifts a Box's actions in, and the bounds there."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from gymnasium import spaces


@dataclass(frozen=True)
class ActionFrame:
    """A Box action space as ESA sees it: ``units = (action - center) / half_width``.

    Attributes:
        box: The action space.
        center: Per dimension, the action at 0 units.
        half_width: Per dimension, the action change of one unit.
        low: The bounds the env clips its actions to, in units.
        high: See ``low``.
        bounded: Whether the sessions clip to ``[low, high]`` (a bounded sample) or not (a
            Gaussian sample, which the env clips).
    """

    box: spaces.Box
    center: np.ndarray
    half_width: np.ndarray
    low: np.ndarray
    high: np.ndarray
    bounded: bool

    @classmethod
    def scaled(cls, box: spaces.Box) -> ActionFrame:
        """The Box mapped to [-1, 1] per bounded dimension (an open side: the raw action)."""
        low, high = box.low.reshape(-1), box.high.reshape(-1)
        finite = np.isfinite(low) & np.isfinite(high)
        center = np.where(finite, (high + low) / 2, 0.0)
        half_width = np.where(finite, (high - low) / 2, 1.0)
        return cls(
            box,
            center,
            half_width,
            (low - center) / half_width,
            (high - center) / half_width,
            False,
        )

    @classmethod
    def squashed(cls, box: spaces.Box) -> ActionFrame:
        """SB3's squashed [-1, 1] (the replay buffer's units), where the sessions are bounded."""
        return cls.unit(box, bounded=True)

    @classmethod
    def unit(cls, box: spaces.Box, *, bounded: bool) -> ActionFrame:
        """Actions already in [-1, 1] per dimension (SB3's squashed ones, RLlib's normalized).

        In the Box's dtype, as :meth:`scaled` gives them for a [-1, 1] Box: the same bits.
        """
        ones = np.ones(int(np.prod(box.shape or ())), dtype=box.dtype)
        return cls(box, np.zeros_like(ones), ones, -ones, ones, bounded)

    @property
    def dim(self) -> int:
        """The action dimension D."""
        return int(self.low.size)

    def session_bounds(self) -> tuple[np.ndarray | None, np.ndarray | None]:
        """The bounds the sessions clip to: ``(low, high)``, or ``(None, None)``."""
        return (self.low, self.high) if self.bounded else (None, None)
