"""Gymnasium environment: a ~1 kg quadrotor on MuJoCo tracking an oriented point along a path."""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np
from gymnasium import spaces

from esa_experiments.envs import quadrotor_model as qm
from esa_experiments.envs.quadrotor_paths import ClosedPath, make_path
from esa_experiments.envs.validation import (
    is_real,
    require,
    require_non_negative,
    require_positive,
)

_TWO_PI = 2.0 * math.pi


class QuadrotorEnv(gym.Env[np.ndarray, np.ndarray]):
    """Quadrotor path tracking, after the PX4/Gazebo task of the ESA paper (Section IV).

    A 1.0 kg "X" quadrotor (arm 0.17 m, see :mod:`~esa_experiments.envs.quadrotor_model`) must
    follow a target: an oriented point (position and yaw) moving along ``path``.

    **Actions** (``Box(-1, 1, (4,), float32)``; values outside are clipped, non-finite values
    raise ``ValueError``). They are setpoints for an on-board attitude loop, like PX4's
    stabilized mode, which makes random exploration survivable for a moment yet still lets it
    crash within seconds:

    ====  ==================  ==========================================================
    idx   name                meaning
    ====  ==================  ==========================================================
    0     collective thrust   ``T = m g (1 + a0)``: 0 at -1, hover at 0, 2 m g at +1
    1     roll                roll setpoint ``a1 * 30 deg`` (+ banks toward body -y)
    2     pitch               pitch setpoint ``a2 * 30 deg`` (+ tilts thrust toward body +x)
    3     yaw                 yaw-rate setpoint ``a3 * 90 deg/s`` (+ turns left, CCW)
    ====  ==================  ==========================================================

    The zero action holds the quadrotor level at hover thrust. Every ``INNER_LOOP_PERIOD``
    (10 ms) the attitude loop computes body torques ``tau_x = Ixx (kp (roll_sp - roll) - kd p)``,
    ``tau_y = Iyy (kp (pitch_sp - pitch) - kd q)``, ``tau_z = Izz k_r (r_sp - r)`` (``p, q, r``
    body rates; ``kp = wn^2``, ``kd = 2 zeta wn``, ``wn = 15 rad/s``, ``zeta = 0.8``,
    ``k_r = 8 /s``) and the mixer (inverse of the rotor wrench matrix) turns ``(T, tau)`` into the
    four rotor thrusts, each saturated to ``[0, 6.13 N]`` by the actuator's ``ctrlrange``; the
    rotor forces and drag torques are then simulated by MuJoCo (5 ms steps). One env step
    (``dt = 0.02`` s) is two attitude-loop updates and four physics steps.

    **Observation** (``Box((12,), float32)``): the 12-D state relative to the target, with
    vectors rotated into the quadrotor's heading frame (world frame turned by the quadrotor's
    yaw: x forward, y left, z up), so the same relative situation gives the same observation
    anywhere on the path. Each component is clipped to the finite space bounds: the arena
    diagonal for positions, ``OBS_MAX_SPEED`` (20 m/s), ``OBS_MAX_ANGULAR_SPEED`` (50 rad/s)
    and the angles' natural ranges; only runaway states that are about to terminate reach them.

    ====  =============================================================================
    idx   component
    ====  =============================================================================
    0-2   position error ``p - p_target`` [m], heading frame
    3-5   velocity error ``v - v_target`` [m/s], heading frame
    6     roll angle [rad] (ZYX Euler)
    7     pitch angle [rad] (ZYX Euler)
    8     yaw error ``yaw - yaw_target`` wrapped to ``[-pi, pi)`` [rad]
    9-11  angular velocity in the inertial frame [rad/s], rotated into the heading frame
    ====  =============================================================================

    **Reward**: ``exp(-(position_weight * |p - p_target| + yaw_weight * |yaw error|))`` in
    ``(0, 1]``: 1 on the target, ~0.37 at 1 m (default weights 1 /m and 0.3 /rad). Being
    positive, it also rewards staying alive, so crashing early never pays.

    **Episode end**: terminated on crash (``z < 0.05`` m), flip (``|roll|`` or ``|pitch|`` above
    ``flip_limit``) or leaving the arena (``|x|`` or ``|y|`` above ``arena_half_width``, ``z``
    above ``arena_height``); truncated after ``episode_duration`` seconds.

    **Start**: at the target's ``t = 0`` pose, at rest and level, displaced by uniform noise
    of ``+-start_position_noise`` per axis and ``+-start_yaw_noise`` in yaw drawn from
    ``np_random`` (seeded by ``reset(seed=...)``).

    **info** (from ``reset`` and ``step``): ``"state"`` the raw 12-D state ``[x, y, z, vx, vy,
    vz, roll, pitch, yaw, wx, wy, wz]`` (world frame, angular velocity in the inertial frame);
    ``"target"`` ``[x, y, z, yaw]`` of the target; ``"position_error"`` [m]; ``"yaw_error"``
    [rad]; ``"time"`` [s]; and on termination ``"termination"``: ``"crash"``, ``"flip"`` or
    ``"out_of_bounds"``.

    Args:
        path: ``"circle"``, ``"eight"`` (lemniscate of Gerono) or ``"hover"``.
        radius: Circle radius, or half the length of the eight [m].
        period: Lap time of the circle or eight [s].
        altitude: Flight altitude of the path [m].
        episode_duration: Time limit [s].
        position_weight: Reward weight of the position error [1/m].
        yaw_weight: Reward weight of the yaw error [1/rad].
        start_position_noise: Half-width of the uniform start position noise per axis [m].
        start_yaw_noise: Half-width of the uniform start yaw noise [rad].
        arena_half_width: Terminate when ``|x|`` or ``|y|`` exceeds it [m].
        arena_height: Terminate when ``z`` exceeds it [m].
        flip_limit: Terminate when ``|roll|`` or ``|pitch|`` exceeds it [rad], in ``(0, pi/2)``.
        render_mode: ``None`` or ``"rgb_array"``.
        width: Rendered image width [px].
        height: Rendered image height [px].
        camera_name: ``"overview"`` (fixed, whole arena) or ``"chase"`` (follows the vehicle).

    Raises:
        ValueError: On an unknown path, render mode or camera, a non-positive size or duration,
            or a path that does not fit in the arena.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": round(1.0 / qm.CONTROL_PERIOD)}

    CRASH_HEIGHT = 0.05
    """Body centre height below which the quadrotor counts as crashed [m]."""

    OBS_MAX_SPEED = 20.0
    """Observed velocity errors are clipped to +- this [m/s]."""

    OBS_MAX_ANGULAR_SPEED = 50.0
    """Observed angular velocities are clipped to +- this [rad/s]."""

    CAMERAS = ("overview", "chase")

    def __init__(
        self,
        path: str = "circle",
        radius: float = 1.5,
        period: float = 15.0,
        altitude: float = 1.5,
        episode_duration: float = 15.0,
        position_weight: float = 1.0,
        yaw_weight: float = 0.3,
        start_position_noise: float = 0.1,
        start_yaw_noise: float = 0.1,
        arena_half_width: float = 4.0,
        arena_height: float = 4.0,
        flip_limit: float = math.radians(80.0),
        render_mode: str | None = None,
        width: int = 640,
        height: int = 480,
        camera_name: str = "overview",
    ) -> None:
        """Build the MuJoCo model and validate the arguments (see the class docstring)."""
        self.path = make_path(path, radius=radius, period=period, altitude=altitude)
        self.path_name = path
        require_positive("episode_duration", episode_duration)
        require_positive("arena_half_width", arena_half_width)
        require_positive("arena_height", arena_height)
        require_non_negative("position_weight", position_weight)
        require_non_negative("yaw_weight", yaw_weight)
        require_non_negative("start_position_noise", start_position_noise)
        require_non_negative("start_yaw_noise", start_yaw_noise)
        require(
            is_real(flip_limit) and 0 < flip_limit < 0.5 * math.pi,
            "flip_limit in (0, pi/2)",
            flip_limit,
        )
        extent = self.path.radius if isinstance(self.path, ClosedPath) else 0.0
        require(
            extent + start_position_noise < arena_half_width,
            f"radius + start_position_noise < arena_half_width = {arena_half_width}",
            extent + start_position_noise,
        )
        require(
            self.CRASH_HEIGHT < altitude - start_position_noise
            and altitude + start_position_noise < arena_height,
            f"altitude +- start_position_noise inside ({self.CRASH_HEIGHT}, {arena_height})",
            altitude,
        )
        require(
            render_mode is None or render_mode in self.metadata["render_modes"],
            f"render_mode None or one of {self.metadata['render_modes']}",
            render_mode,
        )
        require(camera_name in self.CAMERAS, f"camera_name one of {self.CAMERAS}", camera_name)
        require(isinstance(width, int) and width > 0, "width to be an int > 0", width)
        require(isinstance(height, int) and height > 0, "height to be an int > 0", height)

        self.render_mode = render_mode
        self.camera_name = camera_name
        self.dt = qm.CONTROL_PERIOD
        self.position_weight = float(position_weight)
        self.yaw_weight = float(yaw_weight)
        self.start_position_noise = float(start_position_noise)
        self.start_yaw_noise = float(start_yaw_noise)
        self.arena_half_width = float(arena_half_width)
        self.arena_height = float(arena_height)
        self.flip_limit = float(flip_limit)
        self.max_episode_steps = max(1, round(episode_duration / self.dt))

        self.model = mujoco.MjModel.from_xml_string(
            qm.build_quadrotor_mjcf(qm.PHYSICS_TIMESTEP, width, height)
        )
        self.data = mujoco.MjData(self.model)
        self._width, self._height = width, height
        self._renderer: mujoco.Renderer | None = None

        # Cached views and plain-float constants keep the per-step Python small (see the
        # throughput benchmark): MjData arrays are stable views for the data's lifetime.
        self._qpos = self.data.qpos
        self._qvel = self.data.qvel
        self._ctrl = self.data.ctrl
        body = self.model.body("quadrotor").id
        rot: np.ndarray = np.zeros(9)
        mujoco.mju_quat2Mat(rot, self.model.body_iquat[body])
        rot = rot.reshape(3, 3)
        inertia = rot @ np.diag(self.model.body_inertia[body]) @ rot.T
        self._ixx, self._iyy, self._izz = np.diag(inertia).tolist()
        self._hover_thrust = float(self.model.body_subtreemass[body] * -self.model.opt.gravity[2])
        self._mixer = tuple(tuple(row) for row in qm.mixer_matrix().tolist())
        self._kp = qm.ATTITUDE_NATURAL_FREQUENCY**2
        self._kd = 2.0 * qm.ATTITUDE_DAMPING_RATIO * qm.ATTITUDE_NATURAL_FREQUENCY
        self._inner_updates = round(qm.CONTROL_PERIOD / qm.INNER_LOOP_PERIOD)
        self._physics_per_update = round(qm.INNER_LOOP_PERIOD / qm.PHYSICS_TIMESTEP)
        self._step_count = 0

        self.action_space = spaces.Box(-1.0, 1.0, shape=(4,), dtype=np.float32)
        # The arena diagonal bounds every distance between the vehicle and a target inside it.
        reach = math.sqrt(8.0 * arena_half_width**2 + arena_height**2)
        v, w, pi = self.OBS_MAX_SPEED, self.OBS_MAX_ANGULAR_SPEED, math.pi
        high = np.array((reach, reach, reach, v, v, v, pi, 0.5 * pi, pi, w, w, w), dtype=np.float32)
        self.observation_space = spaces.Box(-high, high, dtype=np.float32)
        self._obs_low, self._obs_high = self.observation_space.low, self.observation_space.high

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start a new episode near the target's start pose (see the class docstring)."""
        super().reset(seed=seed)
        mujoco.mj_resetData(self.model, self.data)
        self._step_count = 0
        x, y, z, _, _, _, yaw = self.path.state(0.0)
        noise = self.np_random.uniform(-1.0, 1.0, size=4)
        yaw += self.start_yaw_noise * noise[3]
        self._qpos[:3] = np.array([x, y, z]) + self.start_position_noise * noise[:3]
        self._qpos[3:7] = (math.cos(0.5 * yaw), 0.0, 0.0, math.sin(0.5 * yaw))
        mujoco.mj_forward(self.model, self.data)
        obs, _, info = self._observe()
        return obs, info

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Apply the setpoints for ``dt`` seconds and return the usual 5-tuple."""
        a = np.asarray(action)
        if a.shape != (4,) or a.dtype.kind not in "fiu":
            raise ValueError(
                f"expected a numeric action of shape (4,), got shape {a.shape} of {a.dtype}"
            )
        a0, a1, a2, a3 = a.tolist()
        if not (
            math.isfinite(a0) and math.isfinite(a1) and math.isfinite(a2) and math.isfinite(a3)
        ):
            raise ValueError(f"expected a finite action, got {a.tolist()}")
        thrust = self._hover_thrust * (1.0 + min(1.0, max(-1.0, a0)))
        roll_sp = qm.MAX_TILT * min(1.0, max(-1.0, a1))
        pitch_sp = qm.MAX_TILT * min(1.0, max(-1.0, a2))
        yaw_rate_sp = qm.MAX_YAW_RATE * min(1.0, max(-1.0, a3))
        for _ in range(self._inner_updates):
            self._attitude_loop(thrust, roll_sp, pitch_sp, yaw_rate_sp)
            mujoco.mj_step(self.model, self.data, self._physics_per_update)
        self._step_count += 1

        obs, reward, info = self._observe()
        terminated = "termination" in info
        truncated = not terminated and self._step_count >= self.max_episode_steps
        return obs, reward, terminated, truncated, info

    def _attitude_loop(
        self, thrust: float, roll_sp: float, pitch_sp: float, yaw_rate_sp: float
    ) -> None:
        """Set the rotor thrusts from the setpoints and the current attitude (one update)."""
        _, _, _, qw, qx, qy, qz = self._qpos.tolist()
        _, _, _, p, q, r = self._qvel.tolist()
        roll = math.atan2(2.0 * (qy * qz + qw * qx), 1.0 - 2.0 * (qx * qx + qy * qy))
        pitch = math.asin(min(1.0, max(-1.0, 2.0 * (qw * qy - qx * qz))))
        kp, kd = self._kp, self._kd
        tx = self._ixx * (kp * (roll_sp - roll) - kd * p)
        ty = self._iyy * (kp * (pitch_sp - pitch) - kd * q)
        tz = self._izz * qm.YAW_RATE_GAIN * (yaw_rate_sp - r)
        m0, m1, m2, m3 = self._mixer
        self._ctrl[:] = (
            m0[0] * thrust + m0[1] * tx + m0[2] * ty + m0[3] * tz,
            m1[0] * thrust + m1[1] * tx + m1[2] * ty + m1[3] * tz,
            m2[0] * thrust + m2[1] * tx + m2[2] * ty + m2[3] * tz,
            m3[0] * thrust + m3[1] * tx + m3[2] * ty + m3[3] * tz,
        )

    def _observe(self) -> tuple[np.ndarray, float, dict[str, Any]]:
        """Return the observation, reward and info (with ``"termination"`` if ended) of now."""
        x, y, z, qw, qx, qy, qz = self._qpos.tolist()
        vx, vy, vz, p, q, r = self._qvel.tolist()
        # Rotation matrix body -> world from the unit quaternion.
        r00 = 1.0 - 2.0 * (qy * qy + qz * qz)
        r01 = 2.0 * (qx * qy - qw * qz)
        r02 = 2.0 * (qx * qz + qw * qy)
        r10 = 2.0 * (qx * qy + qw * qz)
        r11 = 1.0 - 2.0 * (qx * qx + qz * qz)
        r12 = 2.0 * (qy * qz - qw * qx)
        r20 = 2.0 * (qx * qz - qw * qy)
        r21 = 2.0 * (qy * qz + qw * qx)
        r22 = 1.0 - 2.0 * (qx * qx + qy * qy)
        roll = math.atan2(r21, r22)
        pitch = math.asin(min(1.0, max(-1.0, -r20)))
        yaw = math.atan2(r10, r00)
        wx = r00 * p + r01 * q + r02 * r
        wy = r10 * p + r11 * q + r12 * r
        wz = r20 * p + r21 * q + r22 * r

        t = self._step_count * self.dt
        tx, ty, tz, tvx, tvy, tvz, tyaw = self.path.state(t)
        ex, ey, ez = x - tx, y - ty, z - tz
        dvx, dvy, dvz = vx - tvx, vy - tvy, vz - tvz
        eyaw = (yaw - tyaw + math.pi) % _TWO_PI - math.pi
        c, s = math.cos(yaw), math.sin(yaw)
        obs = np.array(
            (
                c * ex + s * ey,
                c * ey - s * ex,
                ez,
                c * dvx + s * dvy,
                c * dvy - s * dvx,
                dvz,
                roll,
                pitch,
                eyaw,
                c * wx + s * wy,
                c * wy - s * wx,
                wz,
            ),
            dtype=np.float32,
        )
        np.minimum(obs, self._obs_high, out=obs)
        np.maximum(obs, self._obs_low, out=obs)
        distance = math.sqrt(ex * ex + ey * ey + ez * ez)
        reward = math.exp(-(self.position_weight * distance + self.yaw_weight * abs(eyaw)))
        # One allocation for both info arrays: state and target are views of it.
        raw = np.array((x, y, z, vx, vy, vz, roll, pitch, yaw, wx, wy, wz, tx, ty, tz, tyaw))
        info = {
            "state": raw[:12],
            "target": raw[12:],
            "position_error": distance,
            "yaw_error": eyaw,
            "time": t,
        }
        if z < self.CRASH_HEIGHT:
            info["termination"] = "crash"
        elif abs(roll) > self.flip_limit or abs(pitch) > self.flip_limit:
            info["termination"] = "flip"
        elif max(abs(x), abs(y)) > self.arena_half_width or z > self.arena_height:
            info["termination"] = "out_of_bounds"
        return obs, reward, info

    def render(self) -> np.ndarray | None:
        """Return an RGB image of the scene with the target path drawn, or None without a mode."""
        if self.render_mode is None:
            gym.logger.warn("render() called without render_mode; pass render_mode='rgb_array'.")
            return None
        if self._renderer is None:
            self._renderer = mujoco.Renderer(self.model, self._height, self._width)
        # mj_step leaves the kinematics one physics step behind qpos; refresh them (and the
        # tracking camera) without the rest of mj_forward.
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_camlight(self.model, self.data)
        self._renderer.update_scene(self.data, camera=self.camera_name)
        self._draw_target(self._renderer.scene)
        frame: np.ndarray = self._renderer.render()
        return frame

    def _draw_target(self, scene: mujoco.MjvScene, segments: int = 120) -> None:
        """Append the target (sphere and heading arrow) and its path (polyline) to the scene."""
        tx, ty, tz, _, _, _, tyaw = self.path.state(self._step_count * self.dt)
        centre = np.array([tx, ty, tz])
        heading = centre + 0.25 * np.array([math.cos(tyaw), math.sin(tyaw), 0.0])
        lines: list[tuple[np.ndarray, np.ndarray]] = [(centre, heading)]
        if isinstance(self.path, ClosedPath):
            points = self.path.positions(np.linspace(0.0, self.path.period, segments + 1))
            lines += list(zip(points[:-1], points[1:], strict=True))
        rgba = np.array([0.85, 0.1, 0.1, 0.8], dtype=np.float32)
        shapes = [(mujoco.mjtGeom.mjGEOM_SPHERE, 0.04, centre, centre)]
        shapes += [(mujoco.mjtGeom.mjGEOM_LINE, 3.0, start, end) for start, end in lines]
        for kind, size, start, end in shapes[: scene.maxgeom - scene.ngeom]:
            geom = scene.geoms[scene.ngeom]
            mujoco.mjv_initGeom(geom, kind, np.full(3, size), start, np.eye(3).ravel(), rgba)
            if kind == mujoco.mjtGeom.mjGEOM_LINE:
                mujoco.mjv_connector(geom, kind, size, start, end)
            scene.ngeom += 1

    def close(self) -> None:
        """Free the renderer's GL resources."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
