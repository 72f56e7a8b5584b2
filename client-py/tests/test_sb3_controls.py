"""ESATD3, ESAPPO's target mode, and the controls that credit ESA: the critic's gradient
and the probe as exploration. Real SB3 models on real MuJoCo / classic-control envs,
sessions on the in-process engine (the server path is ESASAC's and ESAPPO's, tested in
test_sb3.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch as th
from stable_baselines3 import PPO, TD3
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.noise import NormalActionNoise

from esa_client import EsaConfig
from esa_client.config import OFF_POLICY_TRUST_REGION
from esa_client.sb3 import ESAPPO, ESASAC, ESATD3

PPO_KWARGS = dict(n_steps=128, batch_size=64, n_epochs=2, policy_kwargs=dict(net_arch=[32]))
OFF_KWARGS = dict(learning_starts=100, batch_size=32, policy_kwargs=dict(net_arch=[32]))


def parameters(model) -> th.Tensor:
    return th.cat([p.detach().flatten() for p in model.policy.parameters()])


def noise(dim: int = 1) -> NormalActionNoise:
    return NormalActionNoise(np.zeros(dim), 0.1 * np.ones(dim))


def ppo(cls, **extra):
    env = make_vec_env("InvertedPendulum-v5", n_envs=2, seed=3)
    model = cls("MlpPolicy", env, seed=3, **PPO_KWARGS, **extra)
    model.learn(4 * 128 * 2)
    return model


def td3(cls, steps: int = 500, **extra):
    env = make_vec_env("Pendulum-v1", n_envs=2, seed=5)
    model = cls("MlpPolicy", env, seed=5, action_noise=noise(), **OFF_KWARGS, **extra)
    model.learn(steps)
    return model


def test_esappo_target_mode_with_learning_rate_zero_is_plain_ppo():
    null = ppo(ESAPPO, esa=EsaConfig(learning_rate=0.0, gate=None), esa_mode="target")
    assert th.equal(parameters(ppo(PPO)), parameters(null))


@pytest.mark.parametrize("shift", ["esc", "gradient"])
def test_esappo_target_mode_executes_the_sample_and_moves_the_policy(shift):
    model = ppo(ESAPPO, esa=EsaConfig(gate=None), esa_mode="target", esa_shift=shift)
    logged = model.logger.name_to_value
    assert logged["esa/target_loss"] > 0
    assert 0 < logged["esa/target_shift_over_std"] <= EsaConfig().trust_region + 1e-6
    # The executed actions are the policy's own samples: PPO's ratio starts at 1.
    buffer = model.rollout_buffer
    obs = th.as_tensor(buffer.observations.reshape(-1, 4))
    actions = th.as_tensor(buffer.actions.reshape(-1, 1))
    model.policy.set_training_mode(False)
    assert th.isfinite(model.policy.evaluate_actions(obs, actions)[1]).all()


def test_esappo_gradient_shift_is_the_trust_region_along_the_head():
    model = ppo(ESAPPO, esa=EsaConfig(gate=None), esa_shift="gradient")
    features = th.zeros(3, 4)
    weights = model._esa_mlp().weights(model._step_features(features))
    shift = model._gradient_shift(weights, 1.0)
    np.testing.assert_allclose(np.linalg.norm(shift, axis=1), EsaConfig().trust_region)
    # Under a fade the control shrinks with ESA's strength.
    faded = model._gradient_shift(weights, 0.25)
    np.testing.assert_allclose(np.linalg.norm(faded, axis=1), 0.25 * EsaConfig().trust_region)


def test_esatd3_with_learning_rate_zero_is_plain_td3():
    null = td3(ESATD3, esa=EsaConfig.off_policy(learning_rate=0.0, gate=None))
    assert null._esa is not None
    plain = td3(TD3)
    assert th.equal(parameters(plain), parameters(null))
    np.testing.assert_array_equal(plain.replay_buffer.actions, null.replay_buffer.actions)


def test_off_policy_drop_ins_default_to_the_off_policy_config():
    for model in (ESATD3("MlpPolicy", "Pendulum-v1"), ESASAC("MlpPolicy", "Pendulum-v1")):
        assert model.esa == EsaConfig.off_policy()
        assert model.esa.trust_region == OFF_POLICY_TRUST_REGION
    assert ESAPPO("MlpPolicy", "InvertedPendulum-v5").esa == EsaConfig()


def test_esatd3_shifts_within_the_trust_region_of_its_noise():
    model = td3(ESATD3, esa=EsaConfig.off_policy(gate=None))
    assert model._esa is not None
    assert np.all(np.abs(model.replay_buffer.actions) <= 1.0)
    assert model._sigma().tolist() == [0.1]


def test_gradient_control_moves_every_action_by_the_bound():
    model = td3(ESATD3, esa=EsaConfig.off_policy(gate=None), esa_shift="gradient")
    assert model._esa is None, "the gradient control opens no session"
    obs, _ = model.policy.obs_to_tensor(np.zeros((2, 3), dtype=np.float32))
    shift = model._gradient_shift(obs, np.zeros((2, 1)), np.full((2, 1), 0.1))
    np.testing.assert_allclose(np.abs(shift), OFF_POLICY_TRUST_REGION * 0.1)


def test_probe_as_exploration_executes_the_sinusoid():
    esa = EsaConfig.off_policy(learning_rate=0.0, gate=None)
    sine = td3(ESATD3, steps=300, esa=esa, esa_execute="probe")
    plain = td3(ESATD3, steps=300, esa=esa)
    executed = sine.replay_buffer.actions[100:300] - plain.replay_buffer.actions[100:300]
    assert np.abs(executed).max() > 0.5 * esa.amplitude, "the probe's sinusoid was executed"


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: ESATD3("MlpPolicy", "Pendulum-v1", esa_action_scale=0.0), "esa_action_scale"),
        (lambda: ESATD3("MlpPolicy", "Pendulum-v1", esa_shift="newton"), "esa_shift"),
        (lambda: ESASAC("MlpPolicy", "Pendulum-v1", esa_execute="mean"), "esa_execute"),
        (
            lambda: ESASAC("MlpPolicy", "Pendulum-v1", esa_shift="gradient", esa_execute="probe"),
            "esa_execute",
        ),
        (lambda: ESAPPO("MlpPolicy", "InvertedPendulum-v5", esa_mode="dpi"), "esa_mode"),
        (lambda: ESAPPO("MlpPolicy", "InvertedPendulum-v5", esa_shift="adam"), "esa_shift"),
        (
            lambda: ESAPPO("MlpPolicy", "InvertedPendulum-v5", esa_target_weight=0),
            "esa_target_weight",
        ),
        (lambda: EsaConfig.off_policy(trust_region=-1.0), "trust_region"),
    ],
)
def test_bad_control_settings_raise_before_training(make, match):
    with pytest.raises(ValueError, match=match):
        make()
