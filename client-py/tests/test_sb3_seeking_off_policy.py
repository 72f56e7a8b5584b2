"""ESASAC's and ESATD3's fade, placebo and shift report. Real SB3 models on real gymnasium
envs, sessions on the in-process engine; a subclass records what each step's ``_shifted``
saw and returned, and ESA's shift under it."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import torch as th
from stable_baselines3 import TD3
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.noise import NormalActionNoise

from esa_client import EsaConfig
from esa_client.sb3 import ESASAC, ESATD3

STEPS = 400
N_ENVS = 2


class Step:
    """One step of a recording model: its inputs and outputs."""

    def __init__(self, model: Any, sampled, mu, sigma, strength, executed, shift) -> None:
        self.timesteps = model.num_timesteps
        self.starts = model._last_episode_starts.copy()
        self.sampled = np.asarray(sampled, dtype=np.float64).copy()
        self.mu = np.asarray(mu, dtype=np.float64).copy()
        self.sigma = sigma.copy()
        self.strength = strength
        self.executed = executed.copy()
        self.shift = shift.copy()


def recording(cls):
    """``cls`` keeping every step's :class:`Step` and the sessions' shift at every step."""

    class Recording(cls):
        def _shifted(self, obs, sampled, mu, sigma, strength):
            executed, shift = super()._shifted(obs, sampled, mu, sigma, strength)
            step = Step(self, sampled, mu, sigma, strength, executed, shift)
            self.__dict__.setdefault("steps", []).append(step)
            return executed, shift

        def _esa_step(self, obs, anchor, sigma, strength):
            applied = super()._esa_step(obs, anchor, sigma, strength)
            self.__dict__.setdefault("esa_shifts", []).append(applied - anchor)
            return applied

    return Recording


def train(cls, env_id: str = "Pendulum-v1", steps: int = STEPS, **extra):
    env = make_vec_env(env_id, n_envs=N_ENVS, seed=5)
    dim = env.action_space.shape[0]
    if issubclass(cls, TD3):
        extra.setdefault("action_noise", NormalActionNoise(np.zeros(dim), 0.1 * np.ones(dim)))
    # A fresh policy_kwargs each time: SB3 writes into the dict it is given.
    kwargs = dict(learning_starts=100, batch_size=32, policy_kwargs=dict(net_arch=[32]))
    model = cls("MlpPolicy", env, seed=5, **kwargs, **extra)
    model.learn(steps)
    return model


def parameters(model) -> th.Tensor:
    return th.cat([p.detach().flatten() for p in model.policy.parameters()])


@pytest.fixture(scope="module")
def plain_td3():
    return train(TD3)


@pytest.mark.parametrize("control", [None, "placebo"])
def test_a_zero_learning_rate_is_plain_td3_with_the_fade_and_the_placebo(plain_td3, control):
    # The placebo's signs come from its own generator: the learner's random stream and
    # actions stay TD3's, bit for bit.
    null = train(
        ESATD3,
        esa=EsaConfig.off_policy(learning_rate=0.0, gate=None, fade=0.5),
        esa_control=control,
    )
    plain = plain_td3
    assert null._esa is not None
    np.testing.assert_array_equal(plain.replay_buffer.actions, null.replay_buffer.actions)
    assert th.equal(parameters(plain), parameters(null))


def test_the_placebo_keeps_esa_sizes_and_draws_signs_at_episode_starts():
    # Reacher-v5: 2 action dimensions and 50-step episodes, so several episode starts.
    model = train(
        recording(ESATD3), "Reacher-v5", esa=EsaConfig.off_policy(gate=None), esa_control="placebo"
    )
    assert len(model.esa_shifts) == len(model.steps) == (STEPS - 100) // N_ENVS
    # Per env and dimension, the placebo's sign in each episode (where ESA's shift is not 0).
    episode = np.zeros(N_ENVS, dtype=int)
    signs: dict[tuple[int, int, int], set[float]] = {}
    for step, esa_shift in zip(model.steps, model.esa_shifts, strict=True):
        placebo = step.shift
        np.testing.assert_array_equal(np.abs(placebo), np.abs(esa_shift))
        np.testing.assert_array_equal(step.executed, np.clip(step.sampled + placebo, -1, 1))
        episode += step.starts
        for env, dim in zip(*np.nonzero(placebo), strict=True):
            signs.setdefault((env, dim, episode[env]), set()).add(np.sign(placebo[env, dim]))
    assert episode.min() >= 3, "the run crosses several episode starts"
    assert all(len(seen) == 1 for seen in signs.values()), "one sign per episode"
    per_dim = {}
    for (env, dim, _), seen in signs.items():
        per_dim.setdefault((env, dim), set()).update(seen)
    assert any(len(seen) == 2 for seen in per_dim.values()), "new signs at episode starts"
    assert np.any([np.any(step.shift != 0) for step in model.steps])


def logged(model) -> dict[str, float]:
    values = model.logger.name_to_value
    report = {key: values[f"esa/{key}"] for key in ("noise_cosine", "at_bound", "undone_by_clip")}
    assert -1 <= report["noise_cosine"] <= 1
    assert 0 <= report["at_bound"] <= 1 and 0 <= report["undone_by_clip"] <= 1
    return report


class Values(dict):
    """A logger for :meth:`EsaRuntime.record`."""

    def record(self, key: str, value: float) -> None:
        self[key] = value


@pytest.mark.parametrize("shift", [None, "gradient", "placebo"])
def test_the_fade_scales_every_shift_to_zero_and_then_esa_steps_nothing(shift):
    esa = EsaConfig.off_policy(gate=None, fade=0.5)
    model = train(recording(ESATD3), esa=esa, esa_control=shift)
    assert [step.timesteps for step in model.steps] == list(range(100, STEPS, N_ENVS))
    for step in model.steps:
        assert step.strength == esa.strength(step.timesteps / STEPS)
        bound = step.strength * esa.trust_region * step.sigma
        assert np.all(np.abs(step.shift) <= bound * (1 + 1e-9))
        if shift == "gradient" and step.strength > 0:
            np.testing.assert_allclose(np.abs(step.shift), bound)  # one dimension: all of it
    faded = [step for step in model.steps if step.strength == 0]
    assert [step.timesteps for step in faded] == list(range(STEPS // 2, STEPS, N_ENVS))
    for step in faded:
        assert not step.shift.any()
        np.testing.assert_array_equal(step.executed, step.sampled)
    assert any(step.shift.any() for step in model.steps)
    report = logged(model)
    if shift == "gradient":
        assert model._esa is None, "the gradient control opens no session"
        assert report["at_bound"] == 1.0
    else:
        values = Values()
        model._esa.record(values)
        assert values["esa/faded_steps"] == len(faded) * N_ENVS


def test_a_loaded_placebo_model_draws_signs_for_its_new_env(tmp_path):
    model = train(ESATD3, steps=160, esa=EsaConfig.off_policy(gate=None), esa_control="placebo")
    assert model._esa_control_shift.directions is not None
    model.save(tmp_path / "model")
    env = make_vec_env("Pendulum-v1", n_envs=3, seed=6)
    # SB3 saves the noise vectorized for the old env count: a new one for the new env.
    noise = NormalActionNoise(np.zeros(1), 0.1 * np.ones(1))
    loaded = ESATD3.load(tmp_path / "model", env=env, action_noise=noise)
    assert loaded.esa_control == "placebo" and loaded._esa_control_shift is None
    loaded.learn(30, reset_num_timesteps=False)
    assert loaded._esa_control_shift.directions.signs.shape == (3, 1)


@pytest.mark.parametrize("cls", [ESASAC, ESATD3])
@pytest.mark.parametrize(
    "extra, name",
    [
        (dict(esa_control="random"), "esa_control"),
        (dict(esa_control="esc"), "esa_control"),
        (dict(esa={"fade": 0.0}), "fade"),
        (dict(esa={"fade": 1.5}), "fade"),
        (dict(esa={"fade": True}), "fade"),
        (dict(esa={"fade": 0.5, "normalize_response": False}), "fade"),
    ],
)
def test_bad_seeking_options_raise_before_training(cls, extra, name):
    with pytest.raises(ValueError, match="^expected") as error:
        cls("MlpPolicy", "Pendulum-v1", **extra)
    assert name in str(error.value)
