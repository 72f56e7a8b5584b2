r"""Physical constants, rotor mixer and MJCF model of the ~1 kg quadrotor.

The airframe is a 330-size "X" quadrotor: arm length 0.17 m (0.34 m motor-to-motor diagonal),
1.0 kg take-off mass split into a hub (battery, flight controller), four arms and four motors
with propellers. MuJoCo derives the inertia from these component geoms, which gives
``Ixx = Iyy ~ 6.0e-3 kg m^2`` and ``Izz ~ 1.2e-2 kg m^2`` (typical for this size class).

Body frame: x forward, y left, z up (FLU); world frame: z up, gravity along -z. Rotors sit at
+-45 degrees from the x axis and are numbered counter-clockwise seen from above::

        front
      0       3          rotor 0: front-left   spins CCW  (reaction torque -z)
        \   /            rotor 1: rear-left    spins CW   (reaction torque +z)
          X              rotor 2: rear-right   spins CCW  (reaction torque -z)
        /   \            rotor 3: front-right  spins CW   (reaction torque +z)
      1       2

Each rotor is a MuJoCo ``motor`` actuator on a site: its control is the rotor thrust ``f_i`` in
newtons, applied along the body z axis, and its gear couples the propeller drag torque
``s_i * YAW_TORQUE_COEFFICIENT * f_i`` about the body z axis. The actuator ``ctrlrange``
``[0, MAX_ROTOR_THRUST]`` is the rotor saturation. Contacts are disabled: the floor is drawn
but never touched, because touching it terminates the episode (crash).
"""

from __future__ import annotations

import math

import numpy as np

GRAVITY = 9.81
"""Gravitational acceleration [m/s^2]."""

ARM_LENGTH = 0.17
"""Distance from the body centre to each rotor axis [m]."""

HUB_MASS = 0.55
"""Hub mass: frame plate, battery, flight controller, ESCs [kg]."""

ARM_MASS = 0.0375
"""Mass of one arm [kg]."""

MOTOR_MASS = 0.075
"""Mass of one motor with its propeller [kg]."""

MASS = HUB_MASS + 4.0 * (ARM_MASS + MOTOR_MASS)
"""Total take-off mass [kg] (1.0)."""

HUB_HALF_SIZE = (0.06, 0.06, 0.03)
"""Half extents of the hub box [m]."""

PROPELLER_RADIUS = 0.1016
"""8-inch propellers [m]; drawn only, they carry no mass of their own."""

THRUST_TO_WEIGHT = 2.5
"""Ratio of the summed maximal rotor thrust to the weight ``MASS * GRAVITY``."""

MAX_ROTOR_THRUST = THRUST_TO_WEIGHT * MASS * GRAVITY / 4.0
"""Saturation of each rotor's thrust [N] (~6.1 N)."""

YAW_TORQUE_COEFFICIENT = 0.016
"""Propeller drag torque per unit thrust [N m / N], a typical value for 8-inch propellers."""

ROTOR_ANGLES = (math.pi / 4.0, 3.0 * math.pi / 4.0, 5.0 * math.pi / 4.0, 7.0 * math.pi / 4.0)
"""Angle of each arm from the body x axis, counter-clockwise [rad]."""

ROTOR_SPIN = (-1.0, 1.0, -1.0, 1.0)
"""Sign of each rotor's reaction torque about body z (diagonal rotors spin the same way)."""

ROTOR_HEIGHT = 0.03
"""Height of the rotor planes above the body origin [m]."""

# Timing: the policy acts every CONTROL_PERIOD; the on-board attitude loop (like PX4's) runs
# faster, every INNER_LOOP_PERIOD, and MuJoCo integrates every PHYSICS_TIMESTEP.
PHYSICS_TIMESTEP = 0.005
"""MuJoCo integration step [s] (200 Hz)."""

INNER_LOOP_PERIOD = 0.01
"""Period of the attitude loop that turns setpoints into rotor thrusts [s] (100 Hz)."""

CONTROL_PERIOD = 0.02
"""Period of the policy's actions, the env's ``dt`` [s] (50 Hz)."""

# Setpoint ranges reached by the normalized actions +-1 (PX4 "stabilized" mode defaults are of
# the same order: 35 deg tilt, 150 deg/s yaw rate).
MAX_TILT = math.radians(30.0)
"""Roll and pitch setpoint at action +-1 [rad]."""

MAX_YAW_RATE = math.radians(90.0)
"""Yaw-rate setpoint at action +-1 [rad/s]."""

ATTITUDE_NATURAL_FREQUENCY = 15.0
"""Natural frequency of the roll and pitch loops [rad/s] (rise time ~0.1 s)."""

ATTITUDE_DAMPING_RATIO = 0.8
"""Damping ratio of the roll and pitch loops."""

YAW_RATE_GAIN = 8.0
"""Bandwidth of the yaw-rate loop [1/s]."""


def rotor_positions() -> np.ndarray:
    """Return the rotor hub positions in the body frame.

    Returns:
        Array of shape (4, 2): the (x, y) of each rotor [m].
    """
    return np.array([(ARM_LENGTH * math.cos(a), ARM_LENGTH * math.sin(a)) for a in ROTOR_ANGLES])


def wrench_matrix() -> np.ndarray:
    """Return the matrix mapping rotor thrusts to collective thrust and body torques.

    ``[T, tau_x, tau_y, tau_z] = wrench_matrix() @ [f_0, f_1, f_2, f_3]`` with
    ``T = sum f_i``, ``tau_x = sum y_i f_i``, ``tau_y = -sum x_i f_i`` and
    ``tau_z = sum s_i k f_i`` (``k`` = :data:`YAW_TORQUE_COEFFICIENT`).

    Returns:
        Array of shape (4, 4).
    """
    xy = rotor_positions()
    return np.stack(
        [
            np.ones(4),
            xy[:, 1],
            -xy[:, 0],
            YAW_TORQUE_COEFFICIENT * np.asarray(ROTOR_SPIN),
        ]
    )


def mixer_matrix() -> np.ndarray:
    """Return the mixer: the inverse of :func:`wrench_matrix`.

    ``f = mixer_matrix() @ [T, tau_x, tau_y, tau_z]`` gives the rotor thrusts that produce a
    desired collective thrust and body torque, before saturation.

    Returns:
        Array of shape (4, 4).
    """
    return np.linalg.inv(wrench_matrix())


def _fmt(values: tuple[float, ...] | np.ndarray) -> str:
    return " ".join(f"{v:.6g}" for v in values)


def build_quadrotor_mjcf(
    timestep: float, offscreen_width: int = 640, offscreen_height: int = 480
) -> str:
    """Build the MJCF text of the quadrotor, the floor and the cameras.

    Args:
        timestep: Physics integration step [s].
        offscreen_width: Width of the offscreen framebuffer, the largest renderable width [px].
        offscreen_height: Height of the offscreen framebuffer [px].

    Returns:
        The MJCF XML document.
    """
    hx, hy, hz = HUB_HALF_SIZE
    xy = rotor_positions()
    # Opposite arms form one straight rod through the centre: the same inertia as two arms,
    # with fewer geoms for MuJoCo to place every step.
    arms = [
        f'<geom name="arms{i}{i + 2}" type="capsule" '
        f'fromto="{_fmt((*xy[i], 0.0))} {_fmt((*xy[i + 2], 0.0))}" size="0.008" '
        f'mass="{2 * ARM_MASS}" material="frame"/>'
        for i in (0, 1)
    ]
    motors, props, sites, actuators = [], [], [], []
    for i, ((x, y), spin) in enumerate(zip(xy, ROTOR_SPIN, strict=True)):
        motors.append(
            f'<geom name="motor{i}" type="cylinder" pos="{x:.6g} {y:.6g} 0" '
            f'size="0.014 {ROTOR_HEIGHT:.6g}" mass="{MOTOR_MASS}" material="motor"/>'
        )
        colour = "prop_ccw" if spin < 0 else "prop_cw"
        props.append(
            f'<geom name="prop{i}" type="cylinder" pos="{x:.6g} {y:.6g} {ROTOR_HEIGHT:.6g}" '
            f'size="{PROPELLER_RADIUS} 0.002" mass="0" material="{colour}"/>'
        )
        sites.append(f'<site name="rotor{i}" pos="{x:.6g} {y:.6g} {ROTOR_HEIGHT:.6g}"/>')
        gear = _fmt((0.0, 0.0, 1.0, 0.0, 0.0, spin * YAW_TORQUE_COEFFICIENT))
        actuators.append(
            f'<motor name="rotor{i}" site="rotor{i}" gear="{gear}" ctrllimited="true" '
            f'ctrlrange="0 {MAX_ROTOR_THRUST:.6g}"/>'
        )
    body = "\n      ".join([*arms, *motors, *props, *sites])
    return f"""<mujoco model="esa_quadrotor">
  <compiler angle="radian" inertiafromgeom="true"/>
  <option timestep="{timestep:.6g}" gravity="0 0 {-GRAVITY}" integrator="Euler">
    <flag contact="disable"/>
  </option>
  <visual>
    <global offwidth="{offscreen_width}" offheight="{offscreen_height}"/>
    <headlight ambient="0.4 0.4 0.4" diffuse="0.6 0.6 0.6"/>
  </visual>
  <asset>
    <texture name="sky" type="skybox" builtin="gradient" rgb1="0.6 0.75 0.9" rgb2="0.2 0.3 0.4"
             width="256" height="256"/>
    <texture name="grid" type="2d" builtin="checker" rgb1="0.25 0.3 0.35" rgb2="0.3 0.35 0.4"
             width="512" height="512" mark="edge" markrgb="0.6 0.6 0.6"/>
    <material name="grid" texture="grid" texrepeat="8 8"/>
    <material name="frame" rgba="0.15 0.15 0.15 1"/>
    <material name="motor" rgba="0.6 0.6 0.65 1"/>
    <material name="prop_ccw" rgba="0.2 0.5 0.9 0.45"/>
    <material name="prop_cw" rgba="0.9 0.5 0.2 0.45"/>
  </asset>
  <worldbody>
    <light pos="0 0 8" dir="0 0 -1" directional="true"/>
    <geom name="floor" type="plane" size="6 6 0.1" material="grid"/>
    <camera name="overview" pos="0 -4.2 3.6" xyaxes="1 0 0 0 0.5 0.866"/>
    <body name="quadrotor" pos="0 0 1">
      <freejoint name="root"/>
      <camera name="chase" mode="trackcom" pos="-1.5 0 0.6" xyaxes="0 -1 0 0.37 0 0.93"/>
      <geom name="hub" type="box" size="{hx} {hy} {hz}" mass="{HUB_MASS}" material="frame"/>
      {body}
    </body>
  </worldbody>
  <actuator>
    {chr(10).join("    " + a for a in actuators).lstrip()}
  </actuator>
</mujoco>
"""
