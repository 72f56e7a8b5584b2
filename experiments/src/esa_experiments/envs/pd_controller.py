"""A hand-written PD reference controller for the quadrotor env, acting on the observation only.

It shows that the task is solvable from the observation alone, and gives the reference
trajectories of ``results/quadrotor/``. It knows nothing about the path: no feed-forward of the
target's acceleration, only feedback on the errors the env observes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from esa_experiments.envs import quadrotor_model as qm


@dataclass(frozen=True)
class PDController:
    """Position PD loop producing the env's normalized thrust/roll/pitch/yaw-rate actions.

    The desired acceleration in the heading frame is ``a = -kp * e_p - kd * e_v`` (per axis,
    from observation components 0-5). Level flight with thrust ``T`` accelerates by
    ``T / m - g`` along z and a small tilt adds ``g * pitch`` along x and ``-g * roll`` along y,
    which gives the setpoints; the thrust is divided by ``cos(roll) cos(pitch)`` so tilting does
    not lose height. The yaw-rate setpoint is ``-yaw_gain * yaw_error``.

    Attributes:
        kp: Horizontal position gain [1/s^2].
        kd: Horizontal velocity gain [1/s].
        kp_z: Vertical position gain [1/s^2].
        kd_z: Vertical velocity gain [1/s].
        yaw_gain: Yaw error gain [1/s].
    """

    kp: float = 4.0
    kd: float = 3.5
    kp_z: float = 6.0
    kd_z: float = 4.5
    yaw_gain: float = 2.0

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        """Return the action for one observation of ``esa_experiments/Quadrotor-v0``.

        Args:
            observation: The env's 12-D observation.

        Returns:
            The action, float32 of shape (4,), within [-1, 1].
        """
        ex, ey, ez, evx, evy, evz, roll, pitch, yaw_error = np.asarray(observation)[:9].tolist()
        g = qm.GRAVITY
        ax = -self.kp * ex - self.kd * evx
        ay = -self.kp * ey - self.kd * evy
        az = -self.kp_z * ez - self.kd_z * evz
        thrust = (1.0 + az / g) / (math.cos(roll) * math.cos(pitch)) - 1.0
        action = np.array(
            (
                thrust,
                -math.atan2(ay, g) / qm.MAX_TILT,
                math.atan2(ax, g) / qm.MAX_TILT,
                -self.yaw_gain * yaw_error / qm.MAX_YAW_RATE,
            ),
            dtype=np.float32,
        )
        return np.clip(action, -1.0, 1.0)
