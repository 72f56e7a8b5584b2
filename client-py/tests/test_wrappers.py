"""EsaActionWrapper on real gymnasium envs against the real server."""

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from reference_law import ReferenceSession

from esa_client import EsaClient, EsaConfig, ServerUnavailable
from esa_client.wrappers import EsaActionWrapper


def q_fn(obs, action):
    """A made-up critic preferring actions near a function of the observation."""
    return -float(np.sum((np.asarray(action) - 0.5 * np.tanh(obs[: action.size])) ** 2))


# check_env's advice for raw envs: wrapping is the point here, and Pendulum's Box is [-2, 2].
@pytest.mark.filterwarnings("ignore:.*different from the unwrapped version")
@pytest.mark.filterwarnings("ignore:.*symmetric and normalized space")
def test_wrapper_passes_check_env(client):
    env = EsaActionWrapper(
        gym.make("Pendulum-v1"), q_fn, esa=EsaConfig(learning_rate=0.5), client=client
    )
    check_env(env, skip_render_check=True)
    env.close()


def test_wrapper_applies_the_improved_action(client):
    esa = EsaConfig(amplitude=0.3, learning_rate=2.0)
    env = EsaActionWrapper(gym.make("InvertedPendulum-v5"), q_fn, esa=esa, client=client)
    applied = []
    inner_step = env.env.step
    env.env.step = lambda action: (applied.append(np.array(action)), inner_step(action))[1]
    reference = ReferenceSession(esa.session_config(1, 0.04, -3.0, 3.0))
    rng = np.random.default_rng(0)
    for episode in range(2):
        obs, _ = env.reset(seed=episode)
        for t in range(30):
            action = rng.uniform(-1, 1, size=1).astype(np.float32)
            probe, want = reference.probe_applied(action, episode_start=t == 0)
            reference.report(
                q_fn(obs, probe.astype(np.float32)), q_reference=q_fn(obs, want.astype(np.float32))
            )
            obs, _, terminated, truncated, info = env.step(action)
            np.testing.assert_allclose(info["esa_action"], want, rtol=1e-6)
            np.testing.assert_array_equal(applied[-1], info["esa_action"])
            if terminated or truncated:
                break
    assert np.any(np.abs(np.array(applied).ravel()) > 0)
    env.close()


def test_wrapper_runs_in_process_by_default_and_starts_no_server():
    env = EsaActionWrapper(gym.make("Pendulum-v1"), q_fn)
    assert env._sessions.client.server is None  # esa-core in this process
    env.reset(seed=0)
    _, _, _, _, info = env.step(env.action_space.sample())
    assert np.all(np.isfinite(info["esa_action"]))
    env.close()


def test_wrapper_leaves_a_client_it_was_given_running(server_bin, monkeypatch):
    monkeypatch.setenv("ESA_SERVER_BIN", server_bin)
    env = EsaActionWrapper(gym.make("Pendulum-v1"), q_fn, client=EsaClient.spawn())
    server = env._sessions.client.server
    env.reset(seed=0)
    env.step(env.action_space.sample())
    env.close()
    # A client passed in stays the caller's: closing the wrapper leaves it running.
    assert server.running()
    env._sessions.client.close()
    assert not server.running()


def test_wrapper_opens_and_closes_the_server_a_string_names(server_bin, monkeypatch):
    monkeypatch.setenv("ESA_SERVER_BIN", server_bin)
    env = EsaActionWrapper(gym.make("Pendulum-v1"), q_fn, client="spawn")
    server = env._sessions.client.server
    assert server is not None and server.running()
    env.close()
    assert not server.running()


def test_wrapper_fails_at_once_where_nothing_listens():
    with pytest.raises(ServerUnavailable, match="127.0.0.1:1"):
        EsaActionWrapper(gym.make("Pendulum-v1"), q_fn, client="127.0.0.1:1")
