"""Short real training runs of ESASAC and ESAPPO against the real server.

They check that the env executes exactly the improved actions the server
returned, that the buffers hold them, that ESA stats reach the logger, and that
save/load round-trips.
"""

import csv

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.logger import configure

from esa_client import EsaConfig, SessionBatch
from esa_client.sb3 import ESAPPO, ESASAC
from esa_client.sb3.runtime import EsaRuntime

N_ENVS = 4
pytestmark = pytest.mark.filterwarnings("ignore:rich is experimental")

# Tiny MLPs run fastest single-threaded; with more threads than free cores torch
# spends its time spinning (10x slower on a busy 2-core machine).
th.set_num_threads(1)


class RecordActions(gym.Wrapper):
    """Keeps every action the env executes."""

    def __init__(self, env):
        super().__init__(env)
        self.actions = []

    def step(self, action):
        self.actions.append(np.array(action, dtype=np.float64))
        return self.env.step(action)


@pytest.fixture
def esa_calls(monkeypatch):
    """Records the sampled actions sent to, and improved actions returned by, the server."""
    calls = {"sampled": [], "improved": []}
    probe, report = SessionBatch.probe, SessionBatch.report

    def recording_probe(self, actions, episode_starts=None, *, steps=None):
        calls["sampled"].append(np.array(actions, dtype=np.float64))
        return probe(self, actions, episode_starts, steps=steps)

    def recording_report(self, q_values, *, steps=None):
        out = report(self, q_values, steps=steps)
        calls["improved"].append(out.copy())
        return out

    monkeypatch.setattr(SessionBatch, "probe", recording_probe)
    monkeypatch.setattr(SessionBatch, "report", recording_report)
    return calls


def logged_columns(path):
    with open(path / "progress.csv") as f:
        rows = list(csv.DictReader(f))
    return {key: [float(r[key]) for r in rows if r.get(key)] for key in rows[0]}


def assert_envs_applied(env, improved, scale):
    for i, wrapped in enumerate(env.envs):
        applied = np.array(wrapped.actions[-len(improved) :])
        np.testing.assert_allclose(applied, scale * improved[:, i], rtol=1e-5, atol=1e-5)


def test_esasac_pendulum(client, esa_calls, tmp_path):
    env = make_vec_env("Pendulum-v1", n_envs=N_ENVS, seed=0, wrapper_class=RecordActions)
    model = ESASAC(
        "MlpPolicy",
        env,
        esa=EsaConfig(learning_rate=0.05),
        esa_address=client.address,
        learning_starts=400,
        batch_size=128,
        policy_kwargs=dict(net_arch=[64, 64]),
        seed=0,
    )
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(2400, progress_bar=True)

    improved, sampled = np.stack(esa_calls["improved"]), np.stack(esa_calls["sampled"])
    assert improved.shape == ((2400 - 400) // N_ENVS, N_ENVS, 1)
    assert_envs_applied(env, improved, scale=2.0)  # Pendulum's Box is [-2, 2]
    end = model.replay_buffer.pos
    stored = model.replay_buffer.actions[end - len(improved) : end]
    np.testing.assert_allclose(stored, improved, atol=1e-6)
    assert np.abs(improved - sampled).max() > 1e-3
    assert np.all(np.abs(improved) <= 1.0)
    columns = logged_columns(tmp_path)
    for key in ("esa/mean_abs_shift", "esa/mean_probe_q", "esa/improvement"):
        assert columns[key] and np.all(np.isfinite(columns[key]))

    model.save(tmp_path / "esasac.zip")
    loaded = ESASAC.load(tmp_path / "esasac.zip", env=env, esa_address=client.address)
    assert loaded.esa == model.esa and loaded._esa is None
    obs = env.reset()
    np.testing.assert_array_equal(
        loaded.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0]
    )
    loaded.learn(200, reset_num_timesteps=False)
    assert loaded._esa is not None
    model.esa_close()
    loaded.esa_close()


class CheckLogProbs(BaseCallback):
    """At each rollout end (policy not yet updated) recomputes the stored log-probs."""

    def __init__(self):
        super().__init__()
        self.max_error = []
        self.last_actions = None

    def _on_step(self):
        return True

    def _on_rollout_end(self):
        buffer = self.model.rollout_buffer
        obs = th.as_tensor(buffer.observations.reshape(-1, buffer.obs_shape[0]))
        actions = th.as_tensor(buffer.actions.reshape(-1, buffer.action_dim))
        with th.no_grad():
            log_probs = self.model.policy.get_distribution(obs).log_prob(actions).numpy()
        self.max_error.append(np.abs(log_probs - buffer.log_probs.reshape(-1)).max())
        self.last_actions = buffer.actions.copy()


def test_esappo_inverted_pendulum(server_bin, esa_calls, monkeypatch, tmp_path):
    monkeypatch.setenv("ESA_SERVER_BIN", server_bin)
    env = make_vec_env("InvertedPendulum-v5", n_envs=N_ENVS, seed=0, wrapper_class=RecordActions)
    model = ESAPPO(
        "MlpPolicy",
        env,
        esa=EsaConfig(learning_rate=0.05),
        n_steps=256,
        batch_size=256,
        n_epochs=4,
        policy_kwargs=dict(net_arch=[64, 64]),
        seed=0,
    )
    model.set_logger(configure(str(tmp_path), ["csv"]))
    check = CheckLogProbs()
    model.learn(3 * 256 * N_ENVS, callback=check, progress_bar=True)

    improved, sampled = np.stack(esa_calls["improved"]), np.stack(esa_calls["sampled"])
    assert improved.shape == (2 * 256, N_ENVS, 1)  # ESA starts once the critic was fitted
    assert_envs_applied(env, improved, scale=1.0)
    np.testing.assert_allclose(check.last_actions, improved[-256:], atol=1e-6)
    assert max(check.max_error) < 1e-4
    assert np.abs(improved - sampled).max() > 1e-3
    columns = logged_columns(tmp_path)
    for key in ("esa/mean_abs_shift", "esa/improvement", "esa/q_loss"):
        assert columns[key] and np.all(np.isfinite(columns[key]))

    server = model._esa.client.server
    model.save(tmp_path / "esappo.zip")
    loaded = ESAPPO.load(tmp_path / "esappo.zip", env=env)
    assert loaded._esa_q_fitted and loaded.esa == model.esa
    for a, b in zip(
        loaded.esa_q_net.state_dict().values(), model.esa_q_net.state_dict().values(), strict=True
    ):
        assert th.equal(a, b)
    model.esa_close()
    assert not server.running() and not server.socket_path.exists()
    loaded.learn(256 * N_ENVS)  # spawns a fresh server for the loaded model
    loaded_server = loaded._esa.client.server
    assert loaded_server.pid != server.pid
    loaded.esa_close()
    assert not loaded_server.running()


@pytest.mark.parametrize("every", [0, -3])
def test_runtime_rejects_a_non_positive_improvement_stride(every):
    # Checked before anything connects: no server, env or sessions are needed.
    with pytest.raises(ValueError, match=f"expected improvement_every >= 1, got {every}"):
        EsaRuntime(EsaConfig(), None, None, np.zeros(1), np.ones(1), improvement_every=every)
