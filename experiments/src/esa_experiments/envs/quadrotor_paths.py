"""Target paths for the quadrotor: an oriented point moving through space over time.

A path maps time ``t`` [s] to the target's position, velocity and yaw. The yaw of a moving
target is its direction of travel (the path tangent), so the quadrotor is asked to fly nose
first; the hovering target keeps a constant yaw of 0.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from esa_experiments.envs.validation import require_positive

PATH_NAMES = ("circle", "eight", "hover")
"""Names accepted by :func:`make_path`."""

TargetState = tuple[float, float, float, float, float, float, float]
"""``(x, y, z, vx, vy, vz, yaw)`` of the target in the world frame [m, m/s, rad]."""


class TargetPath(ABC):
    """A target moving along a path at constant altitude."""

    altitude: float

    @abstractmethod
    def state(self, t: float) -> TargetState:
        """Return the target's ``(x, y, z, vx, vy, vz, yaw)`` at time ``t`` [s]."""

    def positions(self, times: np.ndarray) -> np.ndarray:
        """Return the target positions at the given times as an array of shape (len(times), 3)."""
        return np.array([self.state(float(t))[:3] for t in times]).reshape(-1, 3)


@dataclass(frozen=True)
class HoverPath(TargetPath):
    """A target resting at ``(0, 0, altitude)`` with yaw 0.

    Attributes:
        altitude: Height of the target above the floor [m].
    """

    altitude: float = 1.5

    def __post_init__(self) -> None:
        """Validate the parameters."""
        require_positive("altitude", self.altitude)

    def state(self, t: float) -> TargetState:
        """Return the (constant) target state."""
        return (0.0, 0.0, self.altitude, 0.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True)
class ClosedPath(TargetPath):
    """A closed path of a given size, flown once per period.

    Attributes:
        radius: Size of the path [m] (see the subclass).
        period: Time for one lap [s].
        altitude: Height of the path above the floor [m].
    """

    radius: float = 1.5
    period: float = 15.0
    altitude: float = 1.5

    def __post_init__(self) -> None:
        """Validate the parameters."""
        require_positive("radius", self.radius)
        require_positive("period", self.period)
        require_positive("altitude", self.altitude)


@dataclass(frozen=True)
class CirclePath(ClosedPath):
    """A target circling counter-clockwise (seen from above) around ``(0, 0, altitude)``.

    ``p(t) = (r cos(w t), r sin(w t), altitude)`` with ``r = radius``, ``w = 2 pi / period``;
    it starts at ``(r, 0, altitude)`` heading along +y.
    """

    def state(self, t: float) -> TargetState:
        """Return the target state at time ``t``."""
        w = 2.0 * math.pi / self.period
        c, s = math.cos(w * t), math.sin(w * t)
        r = self.radius
        return (r * c, r * s, self.altitude, -r * w * s, r * w * c, 0.0, w * t + 0.5 * math.pi)


@dataclass(frozen=True)
class EightPath(ClosedPath):
    """A target flying a figure eight (lemniscate of Gerono) centred on ``(0, 0, altitude)``.

    ``p(t) = (r sin(w t), (r / 2) sin(2 w t), altitude)`` with ``r = radius``,
    ``w = 2 pi / period``: the eight spans ``[-r, r]`` along x and ``[-r/2, r/2]`` along y and
    starts at its centre crossing. Its speed never drops to zero, so the heading is defined
    everywhere.
    """

    def state(self, t: float) -> TargetState:
        """Return the target state at time ``t``."""
        w = 2.0 * math.pi / self.period
        r = self.radius
        vx = r * w * math.cos(w * t)
        vy = r * w * math.cos(2.0 * w * t)
        return (
            r * math.sin(w * t),
            0.5 * r * math.sin(2.0 * w * t),
            self.altitude,
            vx,
            vy,
            0.0,
            math.atan2(vy, vx),
        )


def make_path(name: str, radius: float, period: float, altitude: float) -> TargetPath:
    """Create a path by name.

    Args:
        name: One of :data:`PATH_NAMES`.
        radius: Size of the circle or eight [m]; ignored by ``"hover"`` but still validated.
        period: Lap time [s]; ignored by ``"hover"`` but still validated.
        altitude: Flight altitude [m].

    Returns:
        The path.

    Raises:
        ValueError: If the name is unknown or a parameter is not a finite number > 0.
    """
    if name == "circle":
        return CirclePath(radius=radius, period=period, altitude=altitude)
    if name == "eight":
        return EightPath(radius=radius, period=period, altitude=altitude)
    if name == "hover":
        require_positive("radius", radius)
        require_positive("period", period)
        return HoverPath(altitude=altitude)
    raise ValueError(f"expected path to be one of {PATH_NAMES}, got {name!r}")
