"""Adaptive parameter-space noise: the adaptation rule and the PPO/SAC integrations."""

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from esa_client.compare.evaluation import noise_free

from esa_experiments.param_noise import (
    AdaptiveParamNoise,
    PPOParamNoise,
    SACParamNoise,
    action_distance,
)


def test_adapt_moves_sigma_toward_target():
    noise = AdaptiveParamNoise(
        initial_stddev=0.1, desired_action_stddev=0.2, adaptation_coefficient=1.5
    )
    assert noise.adapt(0.1) == pytest.approx(0.15)  # too little action change: grow
    assert noise.adapt(0.3) == pytest.approx(0.1)  # too much: shrink
    assert noise.adapt(0.2) == pytest.approx(0.1 / 1.5)  # at the target counts as too much


def test_adaptation_tracks_target_distance():
    # A policy whose action distance is proportional to sigma (k = 4): sigma must settle
    # around delta / k and stay within one adaptation step of it.
    noise = AdaptiveParamNoise(
        initial_stddev=1.0, desired_action_stddev=0.2, adaptation_coefficient=1.01
    )
    history = [noise.adapt(4.0 * noise.sigma) for _ in range(2000)]
    assert np.allclose(history[-100:], 0.05, rtol=0.011)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"initial_stddev": 0.0}, "initial_stddev"),
        ({"desired_action_stddev": float("nan")}, "desired_action_stddev"),
        ({"adaptation_coefficient": 1.0}, "adaptation_coefficient"),
    ],
)
def test_rejects_bad_settings(kwargs, message):
    with pytest.raises(ValueError, match=message):
        AdaptiveParamNoise(**kwargs)


def test_rejects_non_finite_distance():
    with pytest.raises(ValueError, match="finite"):
        AdaptiveParamNoise().adapt(float("inf"))


def test_sample_has_sigma_scale_and_is_seeded():
    params = {"w": th.zeros(200, 100)}
    a = AdaptiveParamNoise(initial_stddev=0.3, seed=1).sample(params)["w"]
    b = AdaptiveParamNoise(initial_stddev=0.3, seed=1).sample(params)["w"]
    assert th.equal(a, b)
    assert float(a.std()) == pytest.approx(0.3, rel=0.03)


def test_action_distance_is_rms():
    assert action_distance(th.zeros(2, 2), th.tensor([[1.0, 1.0], [1.0, 1.0]])) == pytest.approx(
        1.0
    )


def actor_state(module):
    return {k: v.detach().clone() for k, v in module.state_dict().items()}


def test_ppo_param_noise_perturbs_rollouts_only():
    env = gym.make("Pendulum-v1")
    model = PPOParamNoise(
        "MlpPolicy",
        env,
        n_steps=64,
        batch_size=32,
        n_epochs=1,
        learning_rate=0.0,
        seed=0,
        param_noise={"initial_stddev": 0.5, "adaptation_coefficient": 1.5},
    )
    before = actor_state(model.policy)
    seen = {}

    def during_rollout(locals_, _globals):
        obs = th.as_tensor(locals_["self"]._last_obs)
        with th.no_grad():
            seen["noisy"] = model.policy.get_distribution(obs).distribution.mean.clone()
            with noise_free(model):
                seen["clean"] = model.policy.get_distribution(obs).distribution.mean.clone()
                seen["clean_state"] = actor_state(model.policy)
        return True

    model.learn(128, callback=during_rollout)
    # The rollout acted with a different actor; noise_free gave back the exact clean one.
    assert not th.allclose(seen["noisy"], seen["clean"])
    for key, value in seen["clean_state"].items():
        assert th.allclose(value, before[key], atol=1e-6), key
    # With a zero learning rate, adding and removing eps leaves the parameters as they were.
    for key, value in actor_state(model.policy).items():
        assert th.allclose(value, before[key], atol=1e-6), key
    assert model.param_noise.sigma != 0.5  # adapted after each of the two rollouts


def test_sac_param_noise_acts_with_a_perturbed_copy():
    env = gym.make("Pendulum-v1", max_episode_steps=50)
    model = SACParamNoise(
        "MlpPolicy",
        env,
        learning_starts=10,
        batch_size=16,
        learning_rate=0.0,
        seed=0,
        policy_kwargs={"net_arch": [16, 16]},
        adaptation_interval=10,
    )
    clean_before = actor_state(model.actor)
    first_noisy = actor_state(model._perturbed_actor)
    assert any(
        not th.equal(first_noisy[k], clean_before[k]) for k in clean_before if "log_std" not in k
    )
    sigma0 = model.param_noise.sigma
    model.learn(120)
    assert model.policy.actor is model.actor  # acting swap is undone
    # Episode ends resampled the perturbation; sigma adapted; the trained actor stayed clean.
    later_noisy = actor_state(model._perturbed_actor)
    assert any(not th.equal(first_noisy[k], later_noisy[k]) for k in first_noisy)
    assert model.param_noise.sigma != sigma0
    for key, value in actor_state(model.actor).items():
        assert th.equal(value, clean_before[key]), key


def test_param_noise_models_save_and_load(tmp_path):
    model = PPOParamNoise("MlpPolicy", "Pendulum-v1", n_steps=32, batch_size=32, n_epochs=1, seed=0)
    model.learn(32)
    model.save(tmp_path / "ppo")
    loaded = PPOParamNoise.load(tmp_path / "ppo")
    assert loaded.param_noise_kwargs == model.param_noise_kwargs
    sac = SACParamNoise(
        "MlpPolicy", "Pendulum-v1", learning_starts=5, seed=0, policy_kwargs={"net_arch": [8]}
    )
    sac.learn(10)
    sac.save(tmp_path / "sac")
    assert SACParamNoise.load(tmp_path / "sac").adaptation_interval == 50
