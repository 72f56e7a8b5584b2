"""ESA for Ray RLlib: real runs through a real server (skipped without ``esa-client[rllib]``).

Two EnvRunners x two envs of SAC and of PPO on Pendulum-v1, a few hundred steps each, on
one local Ray instance: the env executes the actions ESA applied (RLlib's unsquash of
the stored ones), the stored actions are ``a_t + v(t)`` with the engine's shift, PPO
stores them unclipped with ``log pi_old(a_t)``, each runner keeps its sessions in its own
process (nothing is started), and the env runners' critics are the learner's. Then learning rate 0
equals plain RLlib bit for bit (see ``test_learning_rate_zero_equals_plain_rllib`` for
where RLlib is deterministic).
"""

import dataclasses
import json
import os
import pickle
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("ray.rllib")

import gymnasium as gym  # noqa: E402
import ray  # noqa: E402
import torch  # noqa: E402
from ray import cloudpickle  # noqa: E402
from ray.rllib.algorithms.ppo import PPOConfig  # noqa: E402
from ray.rllib.algorithms.sac import SACConfig  # noqa: E402
from ray.rllib.core import DEFAULT_MODULE_ID  # noqa: E402
from ray.rllib.core.columns import Columns  # noqa: E402
from ray.rllib.core.distribution.torch.torch_distribution import (  # noqa: E402
    TorchDiagGaussian,
    TorchSquashedGaussian,
)
from ray.tune.registry import register_env  # noqa: E402

from esa_client import EsaConfig, ServerUnavailable  # noqa: E402
from esa_client.compare.execution import start_local_ray  # noqa: E402
from esa_client.rllib import ESA_SHIFT, EsaModuleToEnv, EsaService, with_esa  # noqa: E402

# The env creator below travels to the Ray workers by value (this module is not importable
# there under pytest's importlib mode).
cloudpickle.register_pickle_by_value(sys.modules[__name__])

UNGATED = EsaConfig(gate=None)
ENV = "esa-test-pendulum"


class ExecutedAction(gym.Wrapper):
    """Pendulum-v1 that reports the action it executed in ``info["executed"]``."""

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        return obs, reward, terminated, truncated, {**info, "executed": np.array(action)}


def make_env(_config=None):
    return ExecutedAction(gym.make("Pendulum-v1"))


@pytest.fixture(scope="module")
def ray_session(server_bin, tmp_path_factory):
    """One local Ray instance; its workers find the server binary."""
    saved = {k: os.environ.get(k) for k in ("ESA_SERVER_BIN", "RAY_gcs_server_port_wait_time_s")}
    os.environ.update(ESA_SERVER_BIN=server_bin)
    # A Ray of the tests' own, tried again if Ray's start-up times out on a loaded machine.
    start_local_ray(num_cpus=2)
    register_env(ENV, make_env)
    try:
        yield
    finally:
        ray.shutdown()
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


def sac_config(runners: int, seed: int = 0) -> SACConfig:
    return (
        SACConfig()
        .environment(ENV)
        .env_runners(
            num_env_runners=runners,
            num_envs_per_env_runner=2,
            rollout_fragment_length=25,
            num_cpus_per_env_runner=1,
        )
        .training(num_steps_sampled_before_learning_starts=100, train_batch_size_per_learner=32)
        # SAC's default also runs each iteration for at least 1 s: how many steps it
        # samples and trains then depends on the machine's speed. Steps only here.
        .reporting(min_sample_timesteps_per_iteration=100, min_time_s_per_iteration=0)
        .debugging(seed=seed)
    )


def ppo_config(runners: int, seed: int = 0) -> PPOConfig:
    return (
        PPOConfig()
        .environment(ENV)
        .env_runners(
            num_env_runners=runners,
            num_envs_per_env_runner=2,
            rollout_fragment_length=50,
            num_cpus_per_env_runner=1,
        )
        .training(train_batch_size_per_learner=200, minibatch_size=50, num_epochs=2)
        .debugging(seed=seed)
    )


def esa_connector(runner) -> EsaModuleToEnv:
    return next(c for c in runner._module_to_env.connectors if isinstance(c, EsaModuleToEnv))


def collect(runner):
    """One more sample on a runner: what it stored, what its envs executed, its sessions."""
    episodes = runner.sample(num_timesteps=40, explore=True)
    rows = {"actions": [], "shift": [], "logp": [], "dist": [], "executed": []}
    for episode in episodes:
        n = len(episode)
        if n == 0:
            continue
        rows["actions"].append(np.asarray(episode.get_actions()))
        rows["shift"].append(np.asarray(episode.get_extra_model_outputs(ESA_SHIFT)))
        rows["logp"].append(np.asarray(episode.get_extra_model_outputs(Columns.ACTION_LOGP)))
        rows["dist"].append(np.asarray(episode.get_extra_model_outputs(Columns.ACTION_DIST_INPUTS)))
        rows["executed"].append(np.stack([i["executed"] for i in episode.get_infos()[1:]]))
    connector = esa_connector(runner)
    return {
        **{k: np.concatenate(v) for k, v in rows.items()},
        "address": connector.runtime.client.address,
        "sessions": connector.runtime.batch.ids,
        "state": runner.module.get_state(),
        "pid": os.getpid(),
    }


def learner_state(algo):
    state = algo.learner_group.get_state(components="learner/rl_module")
    return state["learner"]["rl_module"][DEFAULT_MODULE_ID]


def recording_shifts(config):
    """``config`` whose EsaModuleToEnv also stores each step's shift (column ``esa_shift``)."""
    config._module_to_env_connector.kwargs["record_shift"] = True
    return config


def two_runner_run(config, iterations, **esa):
    algo = recording_shifts(with_esa(config, esa=UNGATED, **esa)).build_algo()
    try:
        results = [algo.train() for _ in range(iterations)]
        samples = algo.env_runner_group.foreach_env_runner(collect, local_env_runner=False)
        return results, samples, learner_state(algo)
    finally:
        algo.stop()


def check_in_process(samples):
    """Two runner processes, each with its own in-process sessions: no server anywhere."""
    assert len({s["pid"] for s in samples}) == 2
    assert {s["address"] for s in samples} == {"in-process"}
    assert all(len(s["sessions"]) == 2 for s in samples)  # 2 envs a runner


def test_sac_two_runners_execute_and_store_esa_actions(ray_session):
    results, samples, learner = two_runner_run(sac_config(runners=2), iterations=3)
    assert results[-1]["env_runners"]["esa/mean_abs_shift"] > 0
    assert results[-1]["env_runners"]["esa/active"] > 0
    for s in samples:
        actions, shift = s["actions"], s["shift"]
        assert np.all(np.abs(actions) <= 1.0)  # SAC's squashed space: clipped there
        assert np.mean(np.abs(shift) > 0) > 0.5
        # The env executed RLlib's unsquash of the stored action (Pendulum: [-2, 2]).
        np.testing.assert_allclose(s["executed"], 2.0 * actions, rtol=0, atol=1e-6)
        # The stored action is the sample plus the server's shift; RLlib's logp is the sample's.
        sampled = torch.as_tensor(actions - shift)
        inner = (sampled.abs() < 0.99).all(dim=1)
        dist = TorchSquashedGaussian.from_logits(torch.as_tensor(s["dist"]))
        logp = dist.logp(sampled).numpy()
        np.testing.assert_allclose(logp[inner], s["logp"][inner], rtol=1e-4, atol=1e-4)
        # The env runner probes the learner's target critics (synced after the last update).
        for key in ("target_qf.net.mlp.0.weight", "target_qf_twin.net.mlp.0.weight"):
            matching = [k for k in s["state"] if k.startswith(key.split(".")[0] + ".")]
            assert matching, f"no {key.split('.')[0]} on the env runner"
            for k in matching:
                np.testing.assert_array_equal(s["state"][k], learner[k])
        assert not any(k.startswith(("qf.", "qf_twin.")) for k in s["state"])
    check_in_process(samples)


def test_ppo_two_runners_store_applied_actions_and_behaviour_logp(ray_session):
    results, samples, learner = two_runner_run(ppo_config(runners=2), iterations=2)
    learners = results[-1]["learners"][DEFAULT_MODULE_ID]
    assert np.isfinite(learners["esa/head_loss"])
    assert "esa/gate_correlation" in learners
    for s in samples:
        x, shift = s["actions"], s["shift"]
        assert np.mean(np.abs(shift) > 0) > 0.5
        assert np.any(np.abs(x) > 1.0)  # stored unclipped
        np.testing.assert_allclose(s["executed"], np.clip(2.0 * x, -2.0, 2.0), atol=1e-5)
        dist = TorchDiagGaussian.from_logits(torch.as_tensor(s["dist"]))
        behaviour = dist.logp(torch.as_tensor(x - shift)).numpy()
        # log pi_old(a_t), the exact behaviour log-probability of x = a_t + v(t) ...
        np.testing.assert_allclose(s["logp"], behaviour, rtol=1e-5, atol=1e-5)
        # ... not the policy's density at x.
        assert not np.allclose(s["logp"], dist.logp(torch.as_tensor(x)).numpy())
        # The quadratic head on the env runner is the one the learner fitted.
        head = [k for k in learner if k.startswith("esa_head.")]
        assert head and "esa_active" in s["state"]
        for k in [*head, "esa_active"]:
            np.testing.assert_array_equal(s["state"][k], learner[k])
    check_in_process(samples)


def test_a_runner_goes_on_without_esa_once_its_server_stays_away(ray_session, server_bin):
    """``EsaService(on_unavailable="skip")``: the server dies for good, training goes on."""
    server = subprocess.Popen(
        [server_bin, "--listen", "127.0.0.1:0"], stdout=subprocess.PIPE, text=True
    )
    try:
        line = server.stdout.readline()
        assert line.startswith("listening on "), line
        service = EsaService(
            address=line.split()[-1], timeout=0.5, reconnect_timeout=0.5, on_unavailable="skip"
        )
        algo = with_esa(sac_config(runners=0), esa=UNGATED, service=service).build_algo()
        try:
            # ESA acts once the learner has trained (SAC's first steps are random).
            results = [algo.train()["env_runners"] for _ in range(3)]
            assert results[-1]["esa/mean_abs_shift"] > 0
            server.kill()
            server.wait()
            result = algo.train()["env_runners"]
            assert result["esa/unavailable_steps"] > 0
            assert result["num_env_steps_sampled"] > 0
        finally:
            algo.stop()
    finally:
        server.kill()
        server.wait()


def weights(algo):
    return {k: v for k, v in learner_state(algo).items() if not k.startswith("esa_")}


def local_run(config, iterations):
    algo = config.build_algo()
    buffer = getattr(algo, "local_replay_buffer", None)
    if buffer is not None:
        # RLlib's episode replay buffers draw from an unseeded generator (seed=None).
        buffer.rng = np.random.default_rng(0)
    try:
        for _ in range(iterations):
            algo.train()
        episodes = algo.env_runner.sample(num_timesteps=20, explore=True)
        actions = np.concatenate([np.asarray(e.get_actions()) for e in episodes if len(e)])
        return weights(algo), actions
    finally:
        algo.stop()


@pytest.mark.parametrize("algorithm", ["sac", "ppo"])
def test_learning_rate_zero_equals_plain_rllib(ray_session, algorithm):
    """With learning rate 0, ESA changes no action: weights and samples are plain RLlib's.

    On the local EnvRunner (no remote runners), where RLlib is deterministic for a fixed
    seed once two things are pinned: SAC's iterations are bounded by steps only (its
    default ``min_time_s_per_iteration=1`` makes the amount of training per iteration
    depend on wall time, see ``sac_config``), and its episode replay buffer, whose
    generator RLlib leaves unseeded, draws from a seeded one. The ESA module's extra
    networks are built on a forked torch generator, so they draw nothing from RLlib's.
    """
    make = sac_config if algorithm == "sac" else ppo_config
    plain_weights, plain_actions = local_run(make(runners=0, seed=3), iterations=2)
    config = with_esa(make(runners=0, seed=3), esa=EsaConfig(learning_rate=0.0, gate=None))
    esa_weights, esa_actions = local_run(config, iterations=2)
    assert plain_weights.keys() == esa_weights.keys()
    for key in plain_weights:
        np.testing.assert_array_equal(esa_weights[key], plain_weights[key], err_msg=key)
    np.testing.assert_array_equal(esa_actions, plain_actions)


def test_with_esa_refuses_what_it_cannot_do():
    from ray.rllib.algorithms.dqn import DQNConfig

    with pytest.raises(ValueError, match="SACConfig or PPOConfig"):
        with_esa(DQNConfig())
    with pytest.raises(ValueError, match="EsaConfig"):
        with_esa(PPOConfig(), esa={"amplitude": 0.1})
    # ESAPPO's default fades ESA over half the budget: the budget is needed.
    with pytest.raises(ValueError, match=r"expected budget= the env steps you will train for"):
        with_esa(PPOConfig())
    with pytest.raises(ValueError, match="expected budget a number of env steps"):
        with_esa(PPOConfig(), budget=0)
    with pytest.raises(ValueError, match="esa_control"):
        with_esa(PPOConfig(), budget=1000, control="nothing")
    with pytest.raises(ServerUnavailable, match="127.0.0.1:1"):
        with_esa(SACConfig(), service=EsaService(address="127.0.0.1:1", timeout=1.0))
    config = with_esa(PPOConfig(), budget=10_000)
    # Twice replaces the first connector instead of stacking two.
    factory = with_esa(config, budget=10_000)._module_to_env_connector
    assert factory.previous is None
    assert json.dumps(config.rl_module_spec.model_config["esa"])  # plain data


@pytest.mark.parametrize(
    ("make", "default"), [(SACConfig, EsaConfig.off_policy()), (PPOConfig, EsaConfig.ppo())]
)
def test_with_esa_defaults_as_the_sb3_drop_ins(make, default):
    config = with_esa(make(), budget=100_000)
    assert config._module_to_env_connector.kwargs["esa"] == default
    settings = config.rl_module_spec.model_config["esa"]["config"]
    assert settings == dataclasses.asdict(default)


def test_the_shared_esa_code_imports_without_stable_baselines3():
    # esa_client.rllib runs ESA with the SB3 drop-ins' runtime and quadratic head: those
    # must not pull in stable-baselines3, which esa-client[rllib] does not install.
    code = (
        "import sys; sys.modules['stable_baselines3'] = None\n"
        "import esa_client.rllib.connector, esa_client.rllib.learners\n"
        "assert 'stable_baselines3' not in [m.split('.')[0] for m in sys.modules if sys.modules[m]]"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_ppo_fades_esa_over_the_budget(ray_session):
    """EsaConfig.ppo()'s fade over ``budget``: ESA at full strength first, gone by half."""
    esa = EsaConfig.ppo(gate=None)
    algo = with_esa(ppo_config(runners=0), esa=esa, budget=800).build_algo()
    try:
        # 200 env steps an iteration: the head is fitted after the first; ESA acts from the
        # second at strength 1 - 200 / 400, and is gone from the third on (400 sampled).
        results = [algo.train()["env_runners"] for _ in range(3)]
    finally:
        algo.stop()
    assert results[1]["esa/strength"] == pytest.approx(0.5)
    assert results[1]["esa/mean_abs_shift"] > 0
    assert results[2]["esa/strength"] == 0.0
    assert results[2]["esa/faded_steps"] > 0


@pytest.mark.parametrize("control", ["placebo", "gradient"])
@pytest.mark.parametrize("make", [ppo_config, sac_config], ids=["ppo", "sac"])
def test_the_controls_run_on_rllib(ray_session, make, control):
    config = recording_shifts(with_esa(make(runners=0), esa=UNGATED, control=control))
    algo = config.build_algo()
    try:
        for _ in range(3):
            result = algo.train()
        episodes = [e for e in algo.env_runner.sample(num_timesteps=40, explore=True) if len(e)]
        shift = np.concatenate([np.asarray(e.get_extra_model_outputs(ESA_SHIFT)) for e in episodes])
        actions = np.concatenate([np.asarray(e.get_actions()) for e in episodes])
    finally:
        algo.stop()
    assert result["env_runners"]["esa/active"] > 0
    if make is ppo_config and control == "gradient":
        # The head's gradient, as ESAPPO's: zero past the Box, where the executed action
        # does not move with the sample, and a step of the trust region's size inside.
        sample = np.abs(actions - shift)
        assert np.all(shift[sample > 1.001] == 0) and np.all(shift[sample < 0.999] != 0)
    else:
        assert np.mean(np.abs(shift) > 0) > 0.5, "the control shifts the actions"


def test_the_placebos_directions_follow_the_runners_seed():
    """RLlib's EnvRunner seeds numpy with config.seed + its index before building the
    connector: the placebo's directions repeat for the same seed and differ for another."""
    from esa_client.rllib.connector import EsaModuleToEnv

    def seed_after(global_seed: int) -> int | None:
        np.random.seed(global_seed)
        piece = EsaModuleToEnv(esa=UNGATED, control="placebo")
        copy = pickle.loads(pickle.dumps(piece))
        assert copy._rule.seed == piece._rule.seed  # a copy keeps the runner's directions
        piece.close()
        assert piece._rule.seed == copy._rule.seed  # a reopened runner too
        return piece._rule.seed

    assert seed_after(3) == seed_after(3) != seed_after(4)
    assert EsaModuleToEnv(esa=UNGATED)._rule.__class__.__name__ == "EsaShift"


def test_ppo_shifts_are_esappos_for_the_same_inputs():
    """The same session inputs (head, observations, policy, samples, strength) give the same
    actions, bit for bit, through RLlib's connector and through ``ESAPPO``."""
    pytest.importorskip("stable_baselines3")
    from ray.rllib.algorithms.ppo.ppo_catalog import PPOCatalog
    from ray.rllib.core.rl_module.rl_module import RLModuleSpec
    from stable_baselines3.common.logger import Logger

    from esa_client import EsaClient
    from esa_client.common.runtime import EsaRuntime
    from esa_client.rllib import EsaPPOTorchRLModule
    from esa_client.sb3 import ESAPPO

    esa = EsaConfig.ppo(gate=None)
    model = ESAPPO("MlpPolicy", "Hopper-v5", esa=esa, n_steps=64, batch_size=64, seed=0)
    model.set_logger(Logger(None, []))
    env = model.get_env()
    settings = {"config": dataclasses.asdict(esa), "budget": 1000, "normalize_actions": True}
    module = RLModuleSpec(
        module_class=EsaPPOTorchRLModule,
        catalog_class=PPOCatalog,
        observation_space=env.observation_space,
        action_space=env.action_space,
        model_config={"esa": settings},
        inference_only=True,
    ).build()
    module.esa_head.load_state_dict(model.esa_head.state_dict())
    frame = module.esa_frame
    dt = env.get_attr("dt")[0]
    runtime = EsaRuntime(
        esa,
        EsaClient.in_process(),
        esa.session_config(frame.dim, dt, *frame.session_bounds()),
        1,
        frame.low,
        frame.high,
    )
    connector = EsaModuleToEnv(esa=esa)
    rng = np.random.default_rng(0)
    moved = 0
    for t in range(40):
        obs = torch.as_tensor(rng.normal(size=(1, 11)), dtype=torch.float32)
        mean = torch.as_tensor(rng.normal(scale=0.5, size=(1, 3)), dtype=torch.float32)
        log_std = torch.as_tensor(rng.normal(-0.5, 0.2, size=(1, 3)), dtype=torch.float32)
        sample = (mean + log_std.exp() * torch.randn(1, 3)).numpy()
        starts = np.array([t % 15 == 0])
        strength = 1.0 - t / 80
        model._last_episode_starts = starts
        mean_np, std_np = mean.numpy(), log_std.exp().numpy()
        esappo = model._esa_act(obs, sample, mean_np, std_np, strength)
        rllib = connector._step(
            module, runtime, obs, torch.cat([mean, log_std], dim=1), sample, starts, strength
        )
        np.testing.assert_array_equal(rllib, esappo, err_msg=f"step {t}")
        moved += bool(np.any(rllib != sample))
    assert moved > 30, "ESA shifted the samples (v = 0 at each episode's first step)"
    model.esa_close()
    runtime.close()
