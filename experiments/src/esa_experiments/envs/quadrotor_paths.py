"""Target paths for the quadrotor: an oriented point moving through space over time.

A path maps time ``t`` [s] to the target's position, velocity and yaw. The yaw of a moving
target is its direction of travel (the path tangent), so the quadrotor is asked to fly nose
first; the hovering target keeps a constant yaw of 0.
"""

from __future__ import annotations

import math
import numbers
from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

PATH_NAMES = ("circle", "eight", "hover")
"""Names accepted by :func:`make_path`."""

TargetState = tuple[float, float, float, float, float, float, float]
"""``(x, y, z, vx, vy, vz, yaw)`` of the target in the world frame [m, m/s, rad]."""


def _require_positive(name: str, value: float) -> float:
    valid = isinstance(value, numbers.Real) and not isinstance(value, bool)
    if not (valid and math.isfinite(value) and value > 0):
        raise ValueError(f"expected {name} to be a finite number > 0, got {value!r}")
    return float(value)


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
        _require_positive("altitude", self.altitude)

    def state(self, t: float) -> TargetState:
        """Return the (constant) target state."""
        return (0.0, 0.0, self.altitude, 0.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True)
class CirclePath(TargetPath):
    """A target circling counter-clockwise (seen from above) around ``(0, 0, altitude)``.

    ``p(t) = (r cos(w t), r sin(w t), altitude)`` with ``w = 2 pi / period``; it starts at
    ``(r, 0, altitude)`` heading along +y.

    Attributes:
        radius: Circle radius [m].
        period: Time for one lap [s].
        altitude: Height of the circle above the floor [m].
    """

    radius: float = 1.5
    period: float = 15.0
    altitude: float = 1.5

    def __post_init__(self) -> None:
        """Validate the parameters."""
        _require_positive("radius", self.radius)
        _require_positive("period", self.period)
        _require_positive("altitude", self.altitude)

    def state(self, t: float) -> TargetState:
        """Return the target state at time ``t``."""
        w = 2.0 * math.pi / self.period
        c, s = math.cos(w * t), math.sin(w * t)
        r = self.radius
        return (r * c, r * s, self.altitude, -r * w * s, r * w * c, 0.0, w * t + 0.5 * math.pi)


@dataclass(frozen=True)
class EightPath(TargetPath):
    """A target flying a figure eight (lemniscate of Gerono) centred on ``(0, 0, altitude)``.

    ``p(t) = (r sin(w t), (r / 2) sin(2 w t), altitude)`` with ``w = 2 pi / period``: the eight
    spans ``[-r, r]`` along x and ``[-r/2, r/2]`` along y and starts at its centre crossing.
    Its speed never drops to zero, so the heading is defined everywhere.

    Attributes:
        radius: Half the length of the eight along x [m].
        period: Time for one full eight [s].
        altitude: Height of the eight above the floor [m].
    """

    radius: float = 1.5
    period: float = 15.0
    altitude: float = 1.5

    def __post_init__(self) -> None:
        """Validate the parameters."""
        _require_positive("radius", self.radius)
        _require_positive("period", self.period)
        _require_positive("altitude", self.altitude)

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
        _require_positive("radius", radius)
        _require_positive("period", period)
        return HoverPath(altitude=altitude)
    raise ValueError(f"expected path to be one of {PATH_NAMES}, got {name!r}")
