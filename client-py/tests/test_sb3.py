"""Short real training runs of ESASAC and ESAPPO against the real server.

They check that the env executes exactly Algorithm 1's actions ``a_t + v(t)`` that the
server returned, that the buffers hold them (PPO: unclipped, with the exact behaviour
log-probability), that ESA stats reach the logger, that learning rate 0 reproduces plain
PPO and SAC bit for bit, that bad settings fail before any training, and that save/load
round-trips.
"""

import csv
import math
import time

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3 import PPO, SAC
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.logger import configure
from stable_baselines3.common.noise import NormalActionNoise

from esa_client import EsaClient, EsaConfig, ServerUnavailable, SessionBatch
from esa_client.common.runtime import EsaRuntime
from esa_client.sb3 import ESAPPO, ESASAC, ESATD3
from esa_client.transports.grpc import AheadStepper, GrpcTransport
from esa_client.transports.in_process import InProcessTransport

N_ENVS = 4
pytestmark = pytest.mark.filterwarnings("ignore:rich is experimental")

# Tiny MLPs run fastest single-threaded; with more threads than free cores torch
# spends its time spinning (10x slower on a busy 2-core machine).
th.set_num_threads(1)

# ESA from the first step the critic exists, so that short runs exercise it.
UNGATED = EsaConfig(gate=None)


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
    """Records the sampled actions sent to, and the applied actions returned by, the server.

    A step sent ahead does not call ``probe_applied``: it is recorded by ``AheadStepper.step``.
    """
    calls = {"sampled": [], "applied": [], "scales": []}
    probe_applied = SessionBatch.probe_applied

    def recording(self, actions, episode_starts=None, **kwargs):
        probes, applied = probe_applied(self, actions, episode_starts, **kwargs)
        calls["sampled"].append(np.array(actions, dtype=np.float64))
        calls["applied"].append(applied.copy())
        calls["scales"].append(kwargs.get("action_scales"))
        return probes, applied

    step_ahead = AheadStepper.step

    def recording_ahead(self, batch, call):
        probes, applied = step_ahead(self, batch, call)
        calls["sampled"].append(np.array(call.actions, dtype=np.float64))
        calls["applied"].append(applied.copy())
        calls["scales"].append(call.action_scales)
        return probes, applied

    monkeypatch.setattr(SessionBatch, "probe_applied", recording)
    # A step sent ahead through the gRPC client's stream skips probe_applied.
    monkeypatch.setattr(AheadStepper, "step", recording_ahead)
    return calls


def logged_columns(path):
    with open(path / "progress.csv") as f:
        rows = list(csv.DictReader(f))
    return {key: [float(r[key]) for r in rows if r.get(key)] for key in rows[0]}


def assert_envs_executed(env, applied, low, high, scale=1.0):
    for i, wrapped in enumerate(env.envs):
        executed = np.array(wrapped.actions[-len(applied) :])
        want = scale * np.clip(applied[:, i], low, high)
        np.testing.assert_allclose(executed, want, rtol=1e-5, atol=1e-5)


ESA_STATS = (
    "esa/mean_abs_shift",
    "esa/improvement",
    "esa/shift_over_std",
    "esa/kl_per_dim",
    "esa/clipped_fraction",
)


def test_esasac_pendulum(client, esa_calls, tmp_path):
    env = make_vec_env("Pendulum-v1", n_envs=N_ENVS, seed=0, wrapper_class=RecordActions)
    model = ESASAC(
        "MlpPolicy",
        env,
        esa=EsaConfig(learning_rate=0.2, gate=None),
        esa_client=client,
        learning_starts=400,
        batch_size=128,
        policy_kwargs=dict(net_arch=[64, 64]),
        seed=0,
    )
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(2400, progress_bar=True)

    applied, sampled = np.stack(esa_calls["applied"]), np.stack(esa_calls["sampled"])
    assert applied.shape == ((2400 - 400) // N_ENVS, N_ENVS, 1)
    assert_envs_executed(env, applied, -1.0, 1.0, scale=2.0)  # Pendulum's Box is [-2, 2]
    end = model.replay_buffer.pos
    stored = model.replay_buffer.actions[end - len(applied) : end]
    np.testing.assert_allclose(stored, applied, atol=1e-6)
    assert np.abs(applied - sampled).max() > 1e-3
    assert np.all(np.abs(applied) <= 1.0)
    scales = np.stack(esa_calls["scales"])
    assert np.all((scales > 0) & (scales <= 1.0)), "the squashed policy's local std"
    columns = logged_columns(tmp_path)
    for key in ESA_STATS:
        assert columns[key] and np.all(np.isfinite(columns[key])), key

    model.save(tmp_path / "esasac.zip")
    loaded = ESASAC.load(tmp_path / "esasac.zip", env=env, esa_client=client.address)
    assert loaded.esa == model.esa and loaded._esa is None
    obs = env.reset()
    np.testing.assert_array_equal(
        loaded.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0]
    )
    loaded.learn(200, reset_num_timesteps=False)
    assert loaded._esa is not None
    model.esa_close()
    loaded.esa_close()


class CheckStorage(BaseCallback):
    """At each rollout end (policy not yet updated), checks what the buffer holds."""

    def __init__(self, calls):
        super().__init__()
        self.calls = calls
        self.max_error = []
        self.checked = 0

    def _on_step(self):
        return True

    def _on_rollout_end(self):
        buffer = self.model.rollout_buffer
        n_steps = buffer.buffer_size
        if len(self.calls["sampled"]) < n_steps:
            return  # ESA was not active during this rollout
        # ESAPPO talks to the server in Box units scaled to [-1, 1].
        frame = self.model.esa_frame
        center, half_width = frame.center, frame.half_width
        sampled = np.stack(self.calls["sampled"][-n_steps:]) * half_width + center
        applied = np.stack(self.calls["applied"][-n_steps:]) * half_width + center
        np.testing.assert_allclose(buffer.actions, applied, atol=1e-5)
        obs = th.as_tensor(buffer.observations.reshape(-1, buffer.obs_shape[0]))
        with th.no_grad():
            distribution = self.model.policy.get_distribution(obs)
            log_probs = distribution.log_prob(th.as_tensor(sampled.reshape(-1, 1))).numpy()
        # The stored log-probability is the behaviour's: log pi_old(a_t), not of a_t + v(t).
        self.max_error.append(np.abs(log_probs - buffer.log_probs.reshape(-1)).max())
        self.checked += 1


def test_esappo_inverted_pendulum(server_bin, esa_calls, monkeypatch, tmp_path):
    monkeypatch.setenv("ESA_SERVER_BIN", server_bin)
    env = make_vec_env("InvertedPendulum-v5", n_envs=N_ENVS, seed=0, wrapper_class=RecordActions)
    model = ESAPPO(
        "MlpPolicy",
        env,
        esa=EsaConfig(learning_rate=0.2, gate=None),
        esa_client="spawn",  # a private server, whose lifetime this test follows
        n_steps=256,
        batch_size=256,
        n_epochs=4,
        policy_kwargs=dict(net_arch=[64, 64]),
        seed=0,
    )
    model.set_logger(configure(str(tmp_path), ["csv"]))
    check = CheckStorage(esa_calls)
    model.learn(3 * 256 * N_ENVS, callback=check, progress_bar=True)

    applied, sampled = np.stack(esa_calls["applied"]), np.stack(esa_calls["sampled"])
    assert applied.shape == (2 * 256, N_ENVS, 1)  # ESA starts once the head was fitted
    assert_envs_executed(env, applied, -1.0, 1.0, scale=3.0)  # [-1, 1] units of the [-3, 3] Box
    assert check.checked == 2 and max(check.max_error) < 1e-4
    shift = applied - sampled
    assert np.abs(shift).max() > 1e-3
    stds = np.stack(esa_calls["scales"]).astype(np.float64)
    # v(t) was bounded when step t - 1 was reported, with that step's sigma (kappa = 1).
    assert np.all(shift[0] == 0.0)
    assert np.all(np.abs(shift[1:]) <= stds[:-1] + 1e-9), "the trust region bounds |v| by sigma"
    columns = logged_columns(tmp_path)
    for key in (*ESA_STATS, "esa/head_loss", "esa/active", "esa/gate_correlation"):
        assert columns[key] and np.all(np.isfinite(columns[key])), key

    server = model._esa.client.server
    model.save(tmp_path / "esappo.zip")
    loaded = ESAPPO.load(tmp_path / "esappo.zip", env=env, esa_client="spawn")
    assert loaded.esa == model.esa
    for a, b in zip(
        loaded.esa_head.state_dict().values(), model.esa_head.state_dict().values(), strict=True
    ):
        assert th.equal(a, b)
    model.esa_close()
    assert not server.running() and not server.socket_path.exists()
    loaded.learn(256 * N_ENVS)  # on the fresh server spawned for the loaded model
    loaded_server = loaded._esa.client.server
    assert loaded_server.pid != server.pid and loaded_server.running()
    loaded.esa_close()
    assert not loaded_server.running()


def parameters(model):
    return th.cat([p.detach().reshape(-1) for p in model.policy.parameters()])


@pytest.mark.parametrize("gate", [None, 0.1], ids=["ungated", "gated"])
def test_esappo_with_learning_rate_zero_is_plain_ppo(client, gate):
    kwargs = dict(n_steps=128, batch_size=64, n_epochs=2, policy_kwargs=dict(net_arch=[32]))

    def trained(cls, **extra):
        env = make_vec_env("InvertedPendulum-v5", n_envs=2, seed=3)
        model = cls("MlpPolicy", env, seed=3, **kwargs, **extra)
        model.learn(4 * 128 * 2)
        return model

    plain = trained(PPO)
    null = trained(ESAPPO, esa=EsaConfig(learning_rate=0.0, gate=gate), esa_client=client)
    assert null._esa is not None or gate is not None, "ESA ran (with v = 0)"
    # The same samples and random draws; the decoupled objective's ratio is taken against a
    # second forward pass over the rollout, which rounds differently from the rollout's own.
    assert th.allclose(parameters(plain), parameters(null), atol=1e-4)
    null.esa_close()


@pytest.mark.parametrize("use_sde", [False, True])
def test_esasac_with_learning_rate_zero_is_plain_sac(client, use_sde):
    # ESASAC samples from its own actor call; with gSDE that call carries the latent noise.
    kwargs = dict(
        learning_starts=100, batch_size=32, policy_kwargs=dict(net_arch=[32]), use_sde=use_sde
    )

    def trained(cls, **extra):
        env = make_vec_env("Pendulum-v1", n_envs=2, seed=5)
        model = cls("MlpPolicy", env, seed=5, **kwargs, **extra)
        model.learn(600)
        return model

    plain = trained(SAC)
    null = trained(
        ESASAC,
        esa=EsaConfig(learning_rate=0.0, gate=None),
        esa_client=client,
    )
    assert null._esa is not None
    assert th.equal(parameters(plain), parameters(null))
    np.testing.assert_array_equal(plain.replay_buffer.actions, null.replay_buffer.actions)
    null.esa_close()


@pytest.mark.parametrize("cls", [ESAPPO, ESASAC])
@pytest.mark.parametrize(
    "esa, match",
    [
        (dict(frequency=100.0), "Nyquist"),  # InvertedPendulum: dt 0.04, pi / dt = 78.5
        (dict(amplitude=[0.1, 0.2]), "amplitude"),  # one action dimension
    ],
)
def test_env_dependent_settings_fail_at_construction(cls, esa, match, monkeypatch):
    def never(*args, **kwargs):
        raise AssertionError("no server may be started for a bad config")

    monkeypatch.setattr(EsaRuntime, "__init__", never)
    with pytest.raises(ValueError, match=match):
        cls("MlpPolicy", "InvertedPendulum-v5", esa=EsaConfig(**esa))


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: EsaConfig(amplitude=-1), "amplitude"),
        (lambda: EsaConfig(learning_rate=math.nan), "learning_rate"),
        (lambda: ESAPPO("MlpPolicy", "InvertedPendulum-v5", esa="fast"), "EsaConfig"),
        (
            lambda: ESAPPO(
                "MlpPolicy",
                "InvertedPendulum-v5",
                use_sde=True,
                policy_kwargs={"squash_output": True},
            ),
            "squash_output",
        ),
    ],
)
def test_bad_settings_raise_before_training(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_share_features_extractor_false_trains(client):
    model = ESAPPO(
        "MlpPolicy",
        make_vec_env("InvertedPendulum-v5", n_envs=2, seed=0),
        esa=UNGATED,
        esa_client=client,
        n_steps=64,
        batch_size=64,
        n_epochs=1,
        policy_kwargs=dict(share_features_extractor=False, net_arch=[16]),
        seed=0,
    )
    model.learn(3 * 64 * 2)
    assert model._esa is not None and model._esa_active
    model.esa_close()


def test_a_zero_policy_std_keeps_the_action_instead_of_failing():
    """A squashed policy saturates (sigma = 0 in float32); ESA must not stop training then."""
    config = EsaConfig(gate=None)
    runtime = EsaRuntime(
        config,
        EsaClient.in_process(),
        config.session_config(2, 0.05, -np.ones(2), np.ones(2)),
        2,
        -np.ones(2),
        np.ones(2),
    )
    sampled = np.array([[0.5, -1.0], [0.1, 0.2]])
    std = np.array([[0.3, 0.0], [0.0, 0.0]], dtype=np.float32)
    starts = np.ones(2, dtype=bool)
    for step in range(50):
        applied = runtime.step(sampled, starts if step == 0 else ~starts, lambda x: x.sum(1), std)
        assert np.all(np.isfinite(applied))
        assert np.all(np.abs(applied - sampled)[std == 0] < 1e-30), "no room to move"
    assert np.abs(applied - sampled)[0, 0] > 0, "the other dimension still moves"
    assert np.isfinite(runtime._stats.means()["kl_per_dim"])
    runtime.close()


class Pause(BaseCallback):
    """Sleeps at each rollout end: a trainer whose rollouts are far apart."""

    def __init__(self, seconds):
        super().__init__()
        self.seconds = seconds

    def _on_step(self):
        return True

    def _on_rollout_end(self):
        time.sleep(self.seconds)


def test_sessions_lost_to_the_ttl_are_restored_and_counted(server_bin, monkeypatch, tmp_path):
    server = EsaClient.spawn(server_bin, session_ttl=0.5)
    model = ESAPPO(
        "MlpPolicy",
        make_vec_env("InvertedPendulum-v5", n_envs=2, seed=0),
        esa=UNGATED,
        esa_client=server,
        n_steps=64,
        batch_size=64,
        n_epochs=1,
        policy_kwargs=dict(net_arch=[16]),
        seed=0,
    )
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(4 * 64 * 2, callback=Pause(1.0))
    restored = logged_columns(tmp_path)["esa/sessions_restored"]
    assert sum(restored) >= 2, "every rollout after a pause finds its sessions expired"
    assert server.sessions_restored == sum(restored)
    model.esa_close()
    server.close()


def test_both_engines_train_esappo_alike(server_bin, monkeypatch):
    """The in-process engine and a private server (over gRPC, and over Zenoh) give the same
    actions with the same seed."""
    monkeypatch.setenv("ESA_SERVER_BIN", server_bin)
    runs = {}
    for name, where in (
        ("inprocess", None),
        ("sidecar", "spawn"),  # a spawned server's default client: gRPC
        ("sidecar-zenoh", EsaClient.spawn(server_bin, transport="zenoh")),
    ):
        env = make_vec_env("InvertedPendulum-v5", n_envs=2, seed=4, wrapper_class=RecordActions)
        model = ESAPPO(
            "MlpPolicy",
            env,
            esa=UNGATED,
            esa_client=where,
            n_steps=64,
            batch_size=64,
            n_epochs=2,
            policy_kwargs=dict(net_arch=[16]),
            seed=4,
        )
        model.learn(5 * 64 * 2)
        assert model._esa is not None and model._esa_active
        in_process = isinstance(model._esa.client.transport, InProcessTransport)
        assert in_process == (name == "inprocess")
        grpc = isinstance(model._esa.client.transport, GrpcTransport)
        assert grpc == (name == "sidecar")
        assert (model._esa.client.server is None) == in_process
        runs[name] = ([np.stack(e.actions) for e in env.envs], parameters(model))
        model.esa_close()
        if isinstance(where, EsaClient):
            where.close()
    local_actions, local_parameters = runs.pop("inprocess")
    assert len(local_actions[0]) == 5 * 64
    for server_actions, server_parameters in runs.values():
        for here, there in zip(local_actions, server_actions, strict=True):
            np.testing.assert_array_equal(here, there)
        assert th.equal(local_parameters, server_parameters)


@pytest.mark.parametrize("cls", [ESATD3, ESASAC], ids=["esatd3", "esasac"])
def test_both_engines_train_the_off_policy_drop_ins_alike(server_bin, monkeypatch, cls):
    """In-process and through a sidecar over gRPC (whose steps go ahead, the critic evaluated
    at probes computed here) give the same replay buffer and parameters with the same seed."""
    monkeypatch.setenv("ESA_SERVER_BIN", server_bin)
    runs = []
    for engine in ("in-process", "spawn"):
        env = make_vec_env("Pendulum-v1", n_envs=2, seed=6)
        extra = {"action_noise": NormalActionNoise(np.zeros(1), 0.1 * np.ones(1))}
        model = cls(
            "MlpPolicy",
            env,
            esa=EsaConfig.off_policy(gate=None),
            esa_client=engine,
            learning_starts=100,
            batch_size=32,
            policy_kwargs=dict(net_arch=[32]),
            seed=6,
            **(extra if cls is ESATD3 else {}),
        )
        model.learn(400)
        assert model._esa is not None
        assert isinstance(model._esa.batch._stepper, AheadStepper) == (engine == "spawn")
        runs.append((model.replay_buffer.actions.copy(), parameters(model)))
        model.esa_close()
    (local_actions, local_parameters), (sidecar_actions, sidecar_parameters) = runs
    np.testing.assert_array_equal(local_actions, sidecar_actions)
    assert th.equal(local_parameters, sidecar_parameters)


def test_the_default_engine_is_in_process_unless_a_server_is_named():
    model = ESAPPO("MlpPolicy", "InvertedPendulum-v5", n_steps=64, batch_size=64)
    assert isinstance(model.esa_client.transport, InProcessTransport)
    model.esa_close()


@pytest.mark.parametrize(
    "where, match",
    [
        (3, "expected an EsaClient, a string"),
        ("gpu", "expected 'in-process', 'spawn'"),
        ("inprocess", "expected 'in-process', 'spawn'"),
    ],
)
def test_a_bad_esa_client_fails_at_construction(where, match):
    with pytest.raises(ValueError, match=match):
        ESASAC("MlpPolicy", "Pendulum-v1", esa_client=where)


@pytest.mark.parametrize("cls", [ESAPPO, ESASAC, ESATD3])
def test_an_address_where_nothing_listens_fails_at_construction(cls):
    """Whatever the gate, the server is checked when the model is built, not hours later."""
    start = time.monotonic()
    with pytest.raises(
        ServerUnavailable, match=r"no esa server answered at 127\.0\.0\.1:1 "
    ) as info:
        cls("MlpPolicy", "Pendulum-v1", esa_client="127.0.0.1:1")
    assert time.monotonic() - start < 10.0
    assert "esa_client=None" in info.value.message, "the message names a way out"


def test_a_load_checks_the_server_it_is_given(tmp_path):
    model = ESASAC("MlpPolicy", "Pendulum-v1", learning_starts=10)
    model.save(tmp_path / "esasac.zip")
    with pytest.raises(ServerUnavailable, match="127.0.0.1:1"):
        ESASAC.load(tmp_path / "esasac.zip", esa_client="127.0.0.1:1")
