"""Tests of esa_experiments/Quadrotor-v0: API, physics, feasibility, failure modes, bad input."""

import math
import subprocess
import sys
import warnings

import gymnasium as gym
import mujoco
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from esa_experiments import QUADROTOR_ENV_ID
from esa_experiments.envs import QuadrotorEnv, make_path
from esa_experiments.envs import quadrotor_model as qm
from esa_experiments.envs.pd_controller import PDController
from esa_experiments.envs.quadrotor_rollout import record_episode
from esa_experiments.envs.trajectory_plot import plot_tracking

ZERO = np.zeros(4, dtype=np.float32)


def _gl_unavailable_reason() -> str | None:
    try:
        model = mujoco.MjModel.from_xml_string("<mujoco><worldbody/></mujoco>")
        with mujoco.Renderer(model, 8, 8):
            return None
    except Exception as error:  # any GL failure means: no headless rendering here
        backend = __import__("os").environ.get("MUJOCO_GL")
        return f"no headless OpenGL (MUJOCO_GL={backend!r}; try egl or osmesa): {error}"


GL_UNAVAILABLE = _gl_unavailable_reason()
needs_gl = pytest.mark.skipif(GL_UNAVAILABLE is not None, reason=str(GL_UNAVAILABLE))


def test_make_after_import_gives_the_documented_env():
    env = gym.make(QUADROTOR_ENV_ID, path="eight")
    assert isinstance(env.unwrapped, QuadrotorEnv)
    assert env.unwrapped.path_name == "eight"
    assert env.unwrapped.dt == pytest.approx(0.02)
    assert env.action_space == gym.spaces.Box(-1.0, 1.0, (4,), np.float32)
    assert env.observation_space.shape == (12,)
    assert env.observation_space.dtype == np.float32
    env.close()


def test_make_without_import_via_module_prefixed_id():
    code = (
        "import gymnasium, sys\n"
        "env = gymnasium.make('esa_experiments:esa_experiments/Quadrotor-v0', path='hover')\n"
        "assert 'esa_experiments' in sys.modules\n"
        "print(env.unwrapped.path_name)\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "hover"


@pytest.mark.parametrize("path", ["circle", "eight", "hover"])
def test_check_env_passes_without_warnings(path):
    env = gym.make(QUADROTOR_ENV_ID, path=path).unwrapped
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env, skip_render_check=GL_UNAVAILABLE is not None)
    env.close()


def test_model_is_a_one_kilogram_x_quadrotor():
    env = QuadrotorEnv()
    body = env.model.body("quadrotor")
    assert body.subtreemass[0] == pytest.approx(1.0)
    assert np.allclose(body.ipos, 0.0)
    xy = qm.rotor_positions()
    assert np.allclose(np.hypot(xy[:, 0], xy[:, 1]), 0.17)
    ixx, iyy, izz = env._ixx, env._iyy, env._izz
    assert ixx == pytest.approx(iyy)
    assert 4e-3 < ixx < 1e-2 and 8e-3 < izz < 2e-2 and izz > ixx
    assert np.allclose(qm.mixer_matrix() @ qm.wrench_matrix(), np.eye(4))
    assert env.model.nu == 4
    assert np.allclose(env.model.actuator_ctrlrange, [0.0, qm.MAX_ROTOR_THRUST])


def test_mixer_turns_pure_torques_into_the_matching_rotor_pattern():
    mixer = qm.mixer_matrix()
    hover = mixer @ [qm.MASS * qm.GRAVITY, 0.0, 0.0, 0.0]
    assert np.allclose(hover, qm.MASS * qm.GRAVITY / 4)
    roll = mixer @ [0.0, 1.0, 0.0, 0.0]  # +tau_x: left rotors (0, 1) up, right (2, 3) down
    assert roll[0] > 0 and roll[1] > 0 and roll[2] < 0 and roll[3] < 0
    yaw = mixer @ [0.0, 0.0, 0.0, 1.0]  # +tau_z: more thrust on the CW rotors 1 and 3
    assert np.allclose(np.sign(yaw), qm.ROTOR_SPIN)


@pytest.mark.parametrize("path", ["circle", "eight", "hover"])
def test_zero_action_hovers_within_5_cm_for_2_s(path):
    env = gym.make(QUADROTOR_ENV_ID, path=path)
    _, info = env.reset(seed=3)
    start = info["state"][:3].copy()
    for _ in range(round(2.0 / env.unwrapped.dt)):
        _, _, terminated, truncated, info = env.step(ZERO)
        assert not (terminated or truncated)
        assert np.linalg.norm(info["state"][:3] - start) < 0.05
    assert np.abs(info["state"][6:8]).max() < 1e-3  # still level
    env.close()


@pytest.mark.parametrize("path", ["circle", "eight"])
def test_pd_controller_tracks_the_path_within_20_cm_on_average(path):
    env = gym.make(QUADROTOR_ENV_ID, path=path)
    episode = record_episode(env, PDController(), seed=0)
    assert not episode.terminated
    assert episode.times[-1] == pytest.approx(15.0)
    assert episode.mean_position_error < 0.2
    env.close()


def test_random_actions_crash_within_seconds():
    durations = []
    for seed in range(10):
        env = gym.make(QUADROTOR_ENV_ID, path="circle")
        env.reset(seed=seed)
        env.action_space.seed(seed)
        terminated = truncated = False
        while not (terminated or truncated):
            _, _, terminated, truncated, info = env.step(env.action_space.sample())
        assert terminated and not truncated, f"seed {seed} survived to the time limit"
        assert info["termination"] in ("crash", "flip", "out_of_bounds")
        durations.append(info["time"])
        env.close()
    assert max(durations) < 10.0, durations


def _rollout(env, actions, seed):
    obs, info = env.reset(seed=seed)
    observations, states = [obs], [info["state"]]
    for action in actions:
        obs, _, terminated, truncated, info = env.step(action)
        observations.append(obs)
        states.append(info["state"])
        if terminated or truncated:
            break
    return np.array(observations), np.array(states)


def test_same_seed_same_episode_and_different_seed_different_start():
    actions = np.random.default_rng(0).uniform(-0.3, 0.3, size=(200, 4)).astype(np.float32)
    env_a = gym.make(QUADROTOR_ENV_ID, path="eight")
    env_b = gym.make(QUADROTOR_ENV_ID, path="eight")
    obs_a, states_a = _rollout(env_a, actions, seed=7)
    obs_b, states_b = _rollout(env_b, actions, seed=7)
    np.testing.assert_array_equal(obs_a, obs_b)
    np.testing.assert_array_equal(states_a, states_b)
    obs_c, _ = _rollout(env_a, actions[:1], seed=8)
    assert not np.array_equal(obs_a[0], obs_c[0])


def test_start_is_the_noisy_target_start_pose():
    env = QuadrotorEnv(path="circle", start_position_noise=0.1, start_yaw_noise=0.2)
    for seed in range(5):
        _, info = env.reset(seed=seed)
        state, target = info["state"], info["target"]
        assert np.abs(state[:3] - target[:3]).max() <= 0.1
        assert abs(info["yaw_error"]) <= 0.2
        assert np.allclose(state[3:6], 0.0) and np.allclose(state[6:8], 0.0)
        assert np.allclose(state[9:], 0.0)


def test_observation_is_the_state_relative_to_the_target_in_the_heading_frame():
    env = QuadrotorEnv(path="circle")
    env.reset(seed=1)
    actions = np.random.default_rng(1).uniform(-0.5, 0.5, size=(40, 4))
    for action in actions:
        obs, reward, terminated, _, info = env.step(action)
        assert not terminated
    s, t = info["state"], info["target"]
    x, y, z, vx, vy, vz, roll, pitch, yaw, wx, wy, wz = s
    tvx, tvy, tvz = env.path.state(info["time"])[3:6]
    c, sn = math.cos(yaw), math.sin(yaw)

    def heading(vec):
        return [c * vec[0] + sn * vec[1], -sn * vec[0] + c * vec[1], vec[2]]

    yaw_error = (yaw - t[3] + math.pi) % (2 * math.pi) - math.pi
    expected = [
        *heading([x - t[0], y - t[1], z - t[2]]),
        *heading([vx - tvx, vy - tvy, vz - tvz]),
        roll,
        pitch,
        yaw_error,
        *heading([wx, wy, wz]),
    ]
    np.testing.assert_allclose(obs, expected, rtol=1e-5, atol=1e-5)
    distance = np.linalg.norm(s[:3] - t[:3])
    assert info["position_error"] == pytest.approx(distance)
    assert reward == pytest.approx(math.exp(-(1.0 * distance + 0.3 * abs(yaw_error))))
    # The state's angular velocity is the body rate expressed in the inertial frame.
    rot = env.data.xmat[env.model.body("quadrotor").id].reshape(3, 3)
    np.testing.assert_allclose(s[9:], rot @ env.data.qvel[3:6], atol=1e-9)


def test_roll_pitch_yaw_commands_move_the_vehicle_as_documented():
    env = QuadrotorEnv(path="hover", start_position_noise=0.0, start_yaw_noise=0.0)
    for action, index, sign in [
        ([0.0, 0.5, 0.0, 0.0], 1, -1.0),  # +roll: drift toward -y
        ([0.0, 0.0, 0.5, 0.0], 0, +1.0),  # +pitch: drift toward +x
        ([0.5, 0.0, 0.0, 0.0], 2, +1.0),  # +thrust: climb
    ]:
        _, info = env.reset(seed=0)
        start = info["state"][:3].copy()
        for _ in range(25):
            _, _, _, _, info = env.step(np.array(action))
        assert sign * (info["state"][index] - start[index]) > 0.05
    env.reset(seed=0)
    for _ in range(50):
        _, _, _, _, info = env.step(np.array([0.0, 0.0, 0.0, 0.5]))
    assert info["state"][11] == pytest.approx(0.5 * qm.MAX_YAW_RATE, rel=0.05)  # +yaw: CCW
    tilted = info["state"][6]
    env.reset(seed=0)
    for _ in range(50):
        _, _, _, _, info = env.step(np.array([0.0, 0.4, 0.0, 0.0]))
    assert info["state"][6] == pytest.approx(0.4 * qm.MAX_TILT, abs=0.02)
    assert abs(tilted) < 1e-6


@pytest.mark.parametrize(
    ("qpos", "reason"),
    [
        ([0.0, 0.0, 0.04, 1.0, 0.0, 0.0, 0.0], "crash"),
        ([0.0, 0.0, 1.5, math.cos(0.8), math.sin(0.8), 0.0, 0.0], "flip"),
        ([0.0, 0.0, 1.5, math.cos(0.8), 0.0, math.sin(0.8), 0.0], "flip"),
        ([4.1, 0.0, 1.5, 1.0, 0.0, 0.0, 0.0], "out_of_bounds"),
        ([0.0, -4.1, 1.5, 1.0, 0.0, 0.0, 0.0], "out_of_bounds"),
        ([0.0, 0.0, 4.1, 1.0, 0.0, 0.0, 0.0], "out_of_bounds"),
    ],
)
def test_termination_reasons(qpos, reason):
    env = QuadrotorEnv(path="hover")
    env.reset(seed=0)
    env.data.qpos[:] = qpos
    obs, _, terminated, truncated, info = env.step(ZERO)
    assert terminated and not truncated
    assert info["termination"] == reason
    assert obs in env.observation_space


def test_time_limit_truncates():
    env = QuadrotorEnv(path="hover", episode_duration=0.1)
    env.reset(seed=0)
    results = [env.step(ZERO) for _ in range(5)]
    assert [r[3] for r in results] == [False] * 4 + [True]
    assert not any(r[2] for r in results)
    assert results[-1][4]["time"] == pytest.approx(0.1)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"path": "square"}, "expected path to be one of"),
        ({"radius": 0.0}, "expected radius > 0, got 0.0"),
        ({"radius": -1.0}, "expected radius > 0, got -1.0"),
        ({"path": "eight", "period": 0}, "expected period > 0, got 0"),
        ({"altitude": float("nan")}, "expected altitude > 0, got nan"),
        ({"path": "hover", "radius": -2.0}, "expected radius"),
        ({"radius": True}, "expected radius"),
        ({"episode_duration": 0.0}, "expected episode_duration > 0"),
        ({"position_weight": -1.0}, "expected position_weight >= 0"),
        ({"start_yaw_noise": float("inf")}, "expected start_yaw_noise >= 0"),
        ({"flip_limit": 2.0}, "expected flip_limit in (0, pi/2)"),
        ({"radius": 5.0}, "expected radius + start_position_noise < arena_half_width"),
        ({"altitude": 4.5}, "expected altitude +- start_position_noise inside"),
        ({"render_mode": "ansi"}, "expected render_mode None or one of"),
        ({"camera_name": "top"}, "expected camera_name one of"),
        ({"width": 0}, "expected width to be an int > 0"),
    ],
)
def test_bad_constructor_args_raise_value_error(kwargs, message):
    with pytest.raises(ValueError, match="expected") as error:
        QuadrotorEnv(**kwargs)
    assert message in str(error.value)
    assert ", got " in str(error.value)


@pytest.mark.parametrize(
    "action",
    [np.zeros(3), np.zeros((2, 4)), np.array([0.0, np.nan, 0.0, 0.0]), np.array(["a"] * 4)],
)
def test_bad_actions_raise_and_change_nothing(action):
    env = QuadrotorEnv()
    env.reset(seed=0)
    env.step(ZERO)
    qpos, qvel, time = env.data.qpos.copy(), env.data.qvel.copy(), env.data.time
    with pytest.raises(ValueError, match="expected"):
        env.step(action)
    np.testing.assert_array_equal(env.data.qpos, qpos)
    np.testing.assert_array_equal(env.data.qvel, qvel)
    assert env.data.time == time
    _, _, _, _, info = env.step(ZERO)
    assert info["time"] == pytest.approx(2 * env.dt)


def test_out_of_range_actions_are_clipped():
    env_a, env_b = QuadrotorEnv(), QuadrotorEnv()
    env_a.reset(seed=0)
    env_b.reset(seed=0)
    obs_a = env_a.step(np.array([1e308, -3.0, 2.0, -1e308]))[0]
    obs_b = env_b.step(np.array([1.0, -1.0, 1.0, -1.0]))[0]
    np.testing.assert_array_equal(obs_a, obs_b)


def test_paths_are_consistent():
    for name in ("circle", "eight"):
        path = make_path(name, radius=1.2, period=10.0, altitude=2.0)
        for t in np.linspace(0.0, 10.0, 13):
            x, y, z, vx, vy, vz, yaw = path.state(t)
            ahead = np.array(path.state(t + 1e-6)[:3])
            np.testing.assert_allclose((ahead - [x, y, z]) / 1e-6, [vx, vy, vz], atol=1e-4)
            assert math.atan2(vy, vx) == pytest.approx(math.atan2(math.sin(yaw), math.cos(yaw)))
            assert z == 2.0
        assert np.allclose(path.state(0.0)[:3], path.state(10.0)[:3])  # closed after a period
    circle = make_path("circle", radius=1.2, period=10.0, altitude=2.0)
    positions = circle.positions(np.linspace(0.0, 10.0, 50))
    assert np.allclose(np.hypot(positions[:, 0], positions[:, 1]), 1.2)
    hover = make_path("hover", radius=1.0, period=1.0, altitude=1.0)
    assert hover.state(3.0) == (0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0)


@needs_gl
def test_render_rgb_array_draws_the_scene():
    env = gym.make(QUADROTOR_ENV_ID, path="eight", render_mode="rgb_array", width=160, height=120)
    env.reset(seed=0)
    env.step(ZERO)
    frame = env.render()
    assert frame.shape == (120, 160, 3) and frame.dtype == np.uint8
    assert frame.std() > 10  # not a blank image
    chase = QuadrotorEnv(render_mode="rgb_array", width=160, height=120, camera_name="chase")
    chase.reset(seed=0)
    assert not np.array_equal(chase.render(), frame)
    chase.close()
    env.close()
    env.close()  # closing twice is allowed


def test_render_without_mode_returns_none():
    env = QuadrotorEnv()
    env.reset(seed=0)
    with pytest.warns(UserWarning, match="render_mode"):
        assert env.render() is None


def test_plot_tracking_writes_a_png(tmp_path):
    env = gym.make(QUADROTOR_ENV_ID, path="circle", episode_duration=2.0)
    episode = record_episode(env, PDController(), seed=0)
    out = plot_tracking(episode.targets, {"PD": episode.positions}, tmp_path / "a" / "pd.png")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(ValueError, match="expected target of shape"):
        plot_tracking(np.zeros((5, 2)), {"PD": episode.positions}, tmp_path / "b.png")
    with pytest.raises(ValueError, match="expected at least one flown trajectory"):
        plot_tracking(episode.targets, {}, tmp_path / "c.png")
    assert not (tmp_path / "b.png").exists()
