"""Study ``seeking``'s off-policy methods build the models their arm names say (no training)."""

import math

import numpy as np
import pytest
from esa_client import EsaConfig
from pink import PinkActionNoise
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.noise import NormalActionNoise

from esa_experiments.algorithms import (
    BASELINE_OF,
    SEEKING_FADE,
    SEEKING_OFF_POLICY_ARMS,
    build_model,
    matched_noise_sigma,
    resolve_hyperparams,
)
from esa_experiments.lab.off_policy_arms import ExecutedProbe, MeanAnchor
from esa_experiments.tasks import get_task

ENV = "InvertedDoublePendulum-v5"
TD3_SIGMA = 0.1
"""TD3's noise_sigma in configs/algorithms.toml."""


def build(method: str):
    env = make_vec_env(get_task(ENV).make, n_envs=1, seed=0)
    return build_model(method, env, 0, resolve_hyperparams(method, ENV))


@pytest.mark.parametrize("arm, method", sorted(SEEKING_OFF_POLICY_ARMS.items()))
def test_each_off_policy_arm_builds_what_its_name_says(arm, method):
    model = build(method)
    family = arm.split("_")[0]
    assert arm == family or BASELINE_OF[arm] == family
    assert type(model).__name__.endswith(family.upper())
    if arm == family or arm.endswith("_matched"):
        assert not hasattr(model, "esa"), "plain SB3"
    elif arm == "td3_sine":
        assert model.esa == EsaConfig.off_policy(learning_rate=0.0)
        assert isinstance(model, ExecutedProbe)
    else:
        assert model.esa == EsaConfig.off_policy(fade=SEEKING_FADE)
        control = {"placebo": "placebo", "qgrad": "gradient", "esa": None}[arm.split("_")[-1]]
        assert model.esa_control == control
        assert isinstance(model, MeanAnchor) == ("_mean_" in arm)
        assert not isinstance(model, ExecutedProbe)


def test_the_matched_noise_has_the_variance_of_the_executed_sinusoid():
    amplitude = EsaConfig.off_policy().amplitude
    matched = math.sqrt(TD3_SIGMA**2 + amplitude**2 / 2)
    assert matched_noise_sigma(TD3_SIGMA, "sine") == matched
    assert resolve_hyperparams("td3_gauss_matched", ENV)["noise_sigma"] == matched
    assert resolve_hyperparams("td3", ENV)["noise_sigma"] == TD3_SIGMA
    gauss = build("td3_gauss_matched").action_noise
    assert isinstance(gauss, NormalActionNoise)
    np.testing.assert_array_equal(gauss._sigma, [matched])
    pink = build("td3_pink_matched").action_noise
    assert isinstance(pink, PinkActionNoise)
    np.testing.assert_array_equal(pink.sigma, [matched])


def test_an_unknown_noise_preset_is_refused():
    with pytest.raises(ValueError, match="expected"):
        matched_noise_sigma(TD3_SIGMA, "nope")
