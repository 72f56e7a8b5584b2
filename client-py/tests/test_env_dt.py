"""Where ESA's dt comes from: override, the env's dt, else 1 / render_fps."""

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3.common.env_util import make_vec_env

from esa_client.env_dt import env_dt


class NoClock(gym.Env):
    """An env with neither dt nor render_fps."""

    observation_space = gym.spaces.Box(-1, 1, (1,))
    action_space = gym.spaces.Box(-1, 1, (1,))

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return np.zeros(1, dtype=np.float32), {}

    def step(self, action):
        return np.zeros(1, dtype=np.float32), 0.0, False, False, {}


class FpsOnly(NoClock):
    metadata = {"render_fps": 25}


def test_dt_sources():
    assert env_dt(gym.make("InvertedPendulum-v5")) == pytest.approx(0.04)
    assert env_dt(make_vec_env("Pendulum-v1", n_envs=2)) == 0.05
    assert env_dt(FpsOnly()) == pytest.approx(0.04)
    assert env_dt(NoClock(), override=0.1) == 0.1
    with pytest.raises(ValueError, match=r"EsaConfig\(dt=...\)"):
        env_dt(NoClock())


def test_dt_of_a_gymnasium_vector_env_and_its_wrappers():
    vector = gym.vector.SyncVectorEnv([lambda: gym.make("Pendulum-v1")] * 2)
    assert env_dt(gym.wrappers.vector.RecordEpisodeStatistics(vector)) == 0.05
    assert env_dt(gym.vector.SyncVectorEnv([FpsOnly] * 2)) == pytest.approx(0.04)


def test_a_vector_wrapper_without_a_clock_is_refused_instead_of_guessing():
    from esa_client.vector_wrapper import EsaVectorWrapper

    with pytest.raises(ValueError, match=r"EsaConfig\(dt=...\)"):
        EsaVectorWrapper(gym.vector.SyncVectorEnv([NoClock] * 2), q_fn=lambda o, a: a[:, 0])
