"""The lab's research arms: the subclasses of the drop-ins the studies' runs name.

Real SB3 models on real gymnasium / MuJoCo envs, sessions in-process. The shipped default
is checked against E2's ``ppo_esa`` arm bit for bit, so that E2's verdict is the default's.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch as th
from esa_client import EsaConfig
from esa_client.sb3 import ESAPPO, ESASAC, ESATD3
from stable_baselines3 import PPO, TD3
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.noise import NormalActionNoise

from esa_experiments.algorithms import build_model, esa_class, seeking_methods
from esa_experiments.lab.off_policy_arms import (
    ExecutedProbe,
    MeanAnchor,
    ProbedCritic,
    off_policy_class,
)
from esa_experiments.lab.ppo_arms import (
    ClipObjective,
    LinearHead,
    QNetworkCritic,
    TargetMode,
    esappo_class,
)
from esa_experiments.runs import EXPERIMENTS_DIR
from esa_experiments.studies import seeking
from esa_experiments.training import rl_spec

PPO_KWARGS = dict(n_steps=128, batch_size=64, n_epochs=2, policy_kwargs=dict(net_arch=[32]))


def parameters(model) -> th.Tensor:
    return th.cat([p.detach().flatten() for p in model.policy.parameters()])


def ppo(cls, rollouts: int = 4, **extra):
    env = make_vec_env("InvertedPendulum-v5", n_envs=2, seed=3)
    model = cls("MlpPolicy", env, seed=3, **PPO_KWARGS, **extra)
    model.learn(rollouts * 128 * 2)
    return model


def td3(cls, steps: int = 300, **extra):
    env = make_vec_env("Pendulum-v1", n_envs=2, seed=5)
    noise = NormalActionNoise(np.zeros(1), 0.1 * np.ones(1))
    kwargs = dict(learning_starts=100, batch_size=32, policy_kwargs=dict(net_arch=[32]))
    model = cls("MlpPolicy", env, seed=5, action_noise=noise, **kwargs, **extra)
    model.learn(steps)
    return model


def test_the_shipped_default_is_e2s_ppo_esa_arm_bit_for_bit():
    """ESAPPO() with E2's PPO settings trains as the lab builds E2's ``ppo_esa``."""
    stored = json.loads(
        (EXPERIMENTS_DIR / "results/seeking/runs/Hopper-v5__ppo_esa__s0.json").read_text()
    )["config"]["hyperparams"]
    assert dataclasses.asdict(EsaConfig.ppo()) == stored["esa"]
    assert stored["esa_options"] == {"esa_critic": "quadratic", "esa_objective": "decoupled"}
    method = seeking_methods("ppo", "ppo_fit_quadratic")["ppo_esa"]
    budget = dataclasses.replace(seeking.BUDGETS["smoke"].budgets["InvertedPendulum-v5"])
    spec = rl_spec("seeking", "InvertedPendulum-v5", method, 0, "smoke", budget, variant="ppo_esa")
    spec.config["hyperparams"]["esa"] |= {"trust_region": 1.0, "gate": None}
    hyperparams = spec.config["hyperparams"]
    settings = {k: v for k, v in hyperparams.items() if k not in ("esa", "esa_options", "n_envs")}
    steps = 6 * 4 * settings["n_steps"]

    def trained(make):
        # Built and trained before the next is built: SB3 seeds torch's global generator.
        model = make(make_vec_env("InvertedPendulum-v5", n_envs=4, seed=0))
        model.learn(steps)
        model.esa_close()
        return model

    lab = trained(lambda env: build_model(method, env, 0, hyperparams))
    assert type(lab) is ESAPPO
    net_arch = settings.pop("net_arch")
    shipped = trained(
        lambda env: ESAPPO(
            "MlpPolicy",
            env,
            esa={"gate": None},
            seed=0,
            device="cpu",
            policy_kwargs={"net_arch": net_arch},
            **settings,
        )
    )
    assert shipped._esa_steps > 0, "ESA shifted actions"
    assert th.equal(parameters(lab), parameters(shipped))
    np.testing.assert_array_equal(lab.rollout_buffer.actions, shipped.rollout_buffer.actions)


@pytest.mark.parametrize(
    "options, bases, control",
    [
        ({}, (ClipObjective, LinearHead), None),
        ({"esa_critic": "quadratic", "esa_objective": "decoupled"}, (), None),
        (
            {"esa_critic": "qnet", "esa_objective": "decoupled", "esa_shift": "placebo"},
            (QNetworkCritic,),
            "placebo",
        ),
        ({"esa_mode": "target", "esa_shift": "gradient"}, (TargetMode, ClipObjective), "gradient"),
    ],
)
def test_a_runs_stored_options_name_its_ppo_arm(options, bases, control):
    cls, got = esa_class("ppo", options)
    assert got == control
    assert issubclass(cls, ESAPPO) and all(issubclass(cls, base) for base in bases)
    assert (cls is ESAPPO) == (not bases)


def test_a_runs_stored_options_name_its_off_policy_arm():
    assert esa_class("sac", {})[0] is ESASAC
    cls, control = esa_class("td3", {"esa_anchor": "mean", "esa_shift": "placebo"})
    assert issubclass(cls, MeanAnchor) and issubclass(cls, ESATD3) and control == "placebo"
    assert issubclass(esa_class("td3", {"esa_execute": "probe"})[0], ExecutedProbe)
    probed = off_policy_class("sac", probe_critic="online_min")
    assert issubclass(probed, ProbedCritic) and probed.probe_critic == "online_min"


@pytest.mark.parametrize(
    "family, options, match",
    [
        ("ppo", {"esa_critic": "cubic"}, "critic"),
        ("ppo", {"esa_shift": "newton"}, "esa_shift"),
        ("ppo", {"esa_head_hidden": 32}, "options among"),
        ("td3", {"esa_anchor": "mean", "esa_execute": "probe"}, "execute"),
        ("sac", {"esa_probe_critic": "best"}, "probe_critic"),
    ],
)
def test_unknown_arms_are_refused(family, options, match):
    with pytest.raises(ValueError, match=match):
        esa_class(family, options)


def test_the_clip_objective_with_learning_rate_zero_is_plain_ppo_bit_for_bit():
    null = ppo(esappo_class("linear", "clip"), esa=EsaConfig(learning_rate=0.0, gate=None))
    assert th.equal(parameters(ppo(PPO)), parameters(null))


def test_the_target_mode_with_learning_rate_zero_is_plain_ppo():
    arm = esappo_class("linear", "clip", "target")
    null = ppo(arm, esa=EsaConfig(learning_rate=0.0, gate=None))
    assert th.equal(parameters(ppo(PPO)), parameters(null))


@pytest.mark.parametrize("control", [None, "gradient"])
def test_the_target_mode_executes_the_sample_and_moves_the_policy(control):
    arm = esappo_class("linear", "clip", "target")
    model = ppo(arm, esa=EsaConfig(gate=None), esa_control=control)
    logged = model.logger.name_to_value
    assert logged["esa/target_loss"] > 0
    assert 0 < logged["esa/target_shift_over_std"] <= EsaConfig().trust_region + 1e-6


def test_the_q_network_critic_shifts_within_the_trust_region():
    esa = EsaConfig.ppo(gate=None, trust_region=0.5, fade=None)
    model = ppo(esappo_class("qnet"), esa=esa)
    assert model._esa_steps > 0
    obs = th.as_tensor(model._last_obs)
    sample = np.zeros((2, 1), dtype=np.float32)
    std = np.full((2, 1), 0.4, dtype=np.float32)
    shift = model._session_shift(obs, sample, sample, std, np.zeros(2, bool), 1.0)
    assert np.all(np.abs(shift) <= 0.5 * std * (1 + 1e-9)) and np.any(shift != 0)


def test_the_executed_probe_executes_the_sinusoid():
    esa = EsaConfig.off_policy(learning_rate=0.0, gate=None)
    sine = td3(off_policy_class("td3", execute="probe"), esa=esa)
    plain = td3(ESATD3, esa=esa)
    executed = sine.replay_buffer.actions[100:300] - plain.replay_buffer.actions[100:300]
    assert np.abs(executed).max() > 0.5 * esa.amplitude, "the probe's sinusoid was executed"


@pytest.mark.parametrize("control", [None, "placebo"])
def test_the_mean_anchor_with_learning_rate_zero_is_plain_td3(control):
    esa = EsaConfig.off_policy(learning_rate=0.0, gate=None, fade=0.5)
    null = td3(off_policy_class("td3", anchor="mean"), esa=esa, esa_control=control)
    plain = td3(TD3)
    np.testing.assert_array_equal(plain.replay_buffer.actions, null.replay_buffer.actions)
    assert th.equal(parameters(plain), parameters(null))


def test_the_mean_anchored_gradient_takes_the_critic_at_the_mean():
    cls = off_policy_class("td3", anchor="mean")
    model = td3(cls, esa=EsaConfig.off_policy(gate=None), esa_control="gradient")
    obs, _ = model.policy.obs_to_tensor(np.array([[1.0, 0.0, 0.5], [0.0, 1.0, -2.0]], np.float32))
    sigma = np.full((2, 1), 0.1)
    mu = np.array([[0.3], [-0.2]])
    sampled = np.array([[0.9], [-1.0]], dtype=np.float32)
    executed, shift = model._shifted(obs, sampled, mu, sigma, 0.5)
    np.testing.assert_array_equal(shift, model._gradient_shift(obs, mu, sigma, 0.5))
    np.testing.assert_allclose(np.abs(shift), 0.5 * model.esa.trust_region * sigma)
    np.testing.assert_array_equal(executed, np.clip(sampled + shift, -1, 1))
