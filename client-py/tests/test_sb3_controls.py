"""ESATD3, the drop-ins' defaults, and the controls that credit ESA (``esa_control``): the
critic's gradient and the placebo. Real SB3 models on real MuJoCo / classic-control envs,
sessions on the in-process engine (the server path is ESASAC's and ESAPPO's, tested in
test_sb3.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch as th
from stable_baselines3 import TD3
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


def test_esappo_gradient_shift_is_the_trust_region_along_the_head():
    model = ppo(ESAPPO, esa=EsaConfig.ppo(gate=None, fade=None), esa_control="gradient")
    assert model._esa is None, "the gradient control opens no session"
    obs = th.as_tensor(np.zeros((3, 4), dtype=np.float32))
    sample = np.zeros((3, 1), dtype=np.float32)
    mean, std = np.zeros((3, 1), dtype=np.float32), np.full((3, 1), 0.5, dtype=np.float32)
    shift = model._gradient_shift(obs, sample, mean, std, 1.0)
    np.testing.assert_allclose(np.abs(shift), EsaConfig.ppo().trust_region * 0.5, rtol=1e-6)
    # Under a fade the control shrinks with ESA's strength.
    faded = model._gradient_shift(obs, sample, mean, std, 0.25)
    np.testing.assert_allclose(np.abs(faded), 0.25 * EsaConfig.ppo().trust_region * 0.5, rtol=1e-6)


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
    assert ESAPPO("MlpPolicy", "InvertedPendulum-v5").esa == EsaConfig.ppo()


def test_esatd3_shifts_within_the_trust_region_of_its_noise():
    model = td3(ESATD3, esa=EsaConfig.off_policy(gate=None))
    assert model._esa is not None
    assert np.all(np.abs(model.replay_buffer.actions) <= 1.0)
    assert model._sigma().tolist() == [0.1]


def test_gradient_control_moves_every_action_by_the_bound():
    model = td3(ESATD3, esa=EsaConfig.off_policy(gate=None), esa_control="gradient")
    assert model._esa is None, "the gradient control opens no session"
    obs, _ = model.policy.obs_to_tensor(np.zeros((2, 3), dtype=np.float32))
    shift = model._gradient_shift(obs, np.zeros((2, 1)), np.full((2, 1), 0.1))
    np.testing.assert_allclose(np.abs(shift), OFF_POLICY_TRUST_REGION * 0.1)


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: ESATD3("MlpPolicy", "Pendulum-v1", esa_action_scale=0.0), "esa_action_scale"),
        (lambda: ESATD3("MlpPolicy", "Pendulum-v1", esa_control="newton"), "esa_control"),
        (lambda: ESASAC("MlpPolicy", "Pendulum-v1", esa_control="esc"), "esa_control"),
        (lambda: ESAPPO("MlpPolicy", "InvertedPendulum-v5", esa_control="adam"), "esa_control"),
        (lambda: EsaConfig.off_policy(trust_region=-1.0), "trust_region"),
    ],
)
def test_bad_control_settings_raise_before_training(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_a_research_option_is_not_a_product_argument():
    # The lab's arms are subclasses in experiments/, not options (sb3-contrib's way).
    with pytest.raises(TypeError, match="esa_mode"):
        ESAPPO("MlpPolicy", "InvertedPendulum-v5", esa_mode="target")
