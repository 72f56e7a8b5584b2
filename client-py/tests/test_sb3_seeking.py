"""ESAPPO's ESA that seeks: the quadratic head, the fade, the controls, the decoupled
objective. Real SB3 models on real gymnasium / MuJoCo envs, sessions in-process."""

from __future__ import annotations

import csv

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3 import PPO
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.logger import configure

from esa_client import EsaConfig
from esa_client.common.controls import RandomDirections, shift_report
from esa_client.common.quadratic_head import CriticAtStep, QuadraticHead
from esa_client.sb3 import ESAPPO

PPO_KWARGS = dict(n_steps=128, batch_size=64, n_epochs=2, policy_kwargs=dict(net_arch=[32]))


def parameters(model) -> th.Tensor:
    return th.cat([p.detach().flatten() for p in model.policy.parameters()])


def ppo(cls, env_id: str = "InvertedPendulum-v5", rollouts: int = 4, log=None, **extra):
    env = make_vec_env(env_id, n_envs=2, seed=3)
    model = cls("MlpPolicy", env, seed=3, **PPO_KWARGS, **extra)
    if log is not None:
        model.set_logger(configure(str(log), ["csv"]))
    model.learn(rollouts * 128 * 2)
    return model


def logged(path) -> dict[str, list[float]]:
    """The CSV logger's columns: what each rollout recorded (SB3 clears its values per dump)."""
    with open(path / "progress.csv") as f:
        rows = list(csv.DictReader(f))
    return {key: [float(r[key]) for r in rows if r.get(key)] for key in rows[0]}


@pytest.mark.parametrize("control", [None, "gradient", "placebo"])
def test_esa_and_its_controls_shift_within_the_trust_region_and_log_what_the_shift_did(
    control, tmp_path
):
    esa = EsaConfig.ppo(gate=None, trust_region=0.5, fade=None)
    ppo(ESAPPO, "Hopper-v5", log=tmp_path, esa=esa, esa_control=control)
    columns = logged(tmp_path)
    # The critic is fitted after the first rollout; ESA shifts from the second on.
    assert columns["esa/head_loss"] and all(loss > 0 for loss in columns["esa/head_loss"])
    assert all(-1.0 <= c <= 1.0 for c in columns["esa/noise_cosine"])
    assert all(0.0 <= u <= 1.0 for u in columns["esa/undone_by_clip"])
    assert all(0.0 <= b <= 1.0 for b in columns["esa/at_bound"])
    # Within the trust region (the placebo and gradient shifts are as large as ESA's bound).
    sizes = columns["esa/shift_over_std"]
    assert sizes and all(0.0 < size <= 0.5 + 1e-6 for size in sizes)


def test_quadratic_head_has_its_maximum_where_esc_converges():
    head = QuadraticHead(3, 2, hidden=8)
    features = th.randn(5, 3)
    # With mu = 0 and sigma = 1 the closed form is over z itself: A = c z^2 + g z + offset.
    gain, curvature, _ = head.closed_form(features, np.zeros((5, 2)), np.ones((5, 2)))
    assert (curvature <= 0).all()
    z_star = th.tensor(-gain / (2 * curvature), dtype=th.float32, requires_grad=True)
    (grad,) = th.autograd.grad(head(features, z_star).sum(), z_star)
    assert th.allclose(grad, th.zeros_like(grad), atol=1e-5)


def test_a_critic_at_a_step_is_flat_past_the_box():
    critic = QuadraticHead(3, 2, hidden=8)
    at = CriticAtStep(
        critic,
        th.randn(1, 3),
        np.zeros((1, 2)),
        np.full((1, 2), 0.5),
        np.array([-1.0, -1.0]),
        np.array([1.0, 1.0]),
    )
    assert at(np.array([[3.0, 0.2]]))[0] == pytest.approx(at(np.array([[1.0, 0.2]]))[0])
    gradient = at.gradient(np.array([[3.0, 0.2]]))
    assert gradient[0, 0] == 0.0 and gradient[0, 1] != 0.0


def test_the_placebo_keeps_the_shift_size_and_draws_signs_per_episode():
    placebo = RandomDirections(3, 4, seed=0)
    shift = np.arange(12, dtype=float).reshape(3, 4) - 5.0
    first = placebo(shift, np.array([True, True, True]))
    assert np.array_equal(np.abs(first), np.abs(shift))
    # Mid-episode the signs stay; an episode start redraws that env's only.
    assert np.array_equal(placebo(shift, np.array([False, False, False])), first)
    signs = placebo.signs.copy()
    for _ in range(20):
        placebo(shift, np.array([False, True, False]))
    assert np.array_equal(placebo.signs[[0, 2]], signs[[0, 2]])
    assert set(np.unique(placebo.signs)) <= {-1.0, 1.0}


@pytest.mark.parametrize(
    ("shift", "starts", "match"),
    [
        (np.zeros((2, 4)), np.array([True, True, True]), "shape"),
        (np.zeros((3, 4)), np.array([True]), "episode_starts"),
    ],
)
def test_the_placebo_refuses_bad_shapes(shift, starts, match):
    with pytest.raises(ValueError, match=match):
        RandomDirections(3, 4, seed=0)(shift, starts)


def test_shift_report_measures_noise_removal_bound_and_clip():
    sampled = np.array([[0.5, 2.0]])
    mean = np.zeros((1, 2))
    std = np.ones((1, 2))
    shift = np.array([[-0.5, -0.5]])
    report = shift_report(sampled, shift, mean, std, -np.ones(2), np.ones(2), bound=0.5)
    assert report["at_bound"] == 1.0
    # The second dimension's sample lies past the bound by more than the shift.
    assert report["undone_by_clip"] == 0.5
    assert report["noise_cosine"] == pytest.approx((0.25 + 1.0) / (np.sqrt(0.5) * np.sqrt(4.25)))


def test_the_fade_falls_linearly_to_zero():
    esa = EsaConfig(fade=0.5)
    assert [esa.strength(p) for p in (0.0, 0.25, 0.5, 0.9)] == [1.0, 0.5, 0.0, 0.0]
    assert EsaConfig().strength(0.9) == 1.0


@pytest.mark.parametrize(
    ("fields", "match"),
    [
        ({"fade": 0.0}, "fade"),
        ({"fade": 1.5}, "fade"),
        ({"fade": True}, "fade"),
        ({"fade": 0.5, "normalize_response": False}, "normalize_response=True with fade"),
    ],
)
def test_a_bad_fade_is_refused(fields, match):
    with pytest.raises(ValueError, match=match):
        EsaConfig(**fields)


def test_a_faded_esappo_executes_the_samples_once_the_fade_is_over(tmp_path):
    model = ppo(ESAPPO, esa=EsaConfig.ppo(gate=None), rollouts=4, log=tmp_path)
    # Fitted after rollout 1, ESA fades from 1/2 to 0 over rollout 2 and is off after it.
    assert len(logged(tmp_path)["esa/strength"]) == 1
    assert 0.0 < logged(tmp_path)["esa/strength"][0] <= 0.5
    # Once the fade is over nothing probes the critic again: it is fitted after rollout 1 only.
    assert len(logged(tmp_path)["esa/head_loss"]) == 1
    runtime = model._esa_runtime()
    before = runtime.batch.steps.copy()
    sample = np.array([[0.3], [-0.2]])
    applied = runtime.step(sample, np.zeros(2, bool), lambda a: a[:, 0], strength=0.0)
    assert np.array_equal(applied, sample)
    assert np.array_equal(runtime.batch.steps, before)


def test_the_decoupled_objective_without_a_shift_is_ppos():
    decoupled = ppo(ESAPPO, esa=EsaConfig.ppo(learning_rate=0.0, gate=None))
    # pi_old at the executed action is the behaviour density: weight 1, the same ratio, up
    # to the rounding of one forward pass over the rollout against the rollout's own.
    assert th.allclose(parameters(ppo(PPO)), parameters(decoupled), atol=1e-4)


def test_the_decoupled_objective_trains_with_large_shifts():
    model = ppo(ESAPPO, esa=EsaConfig.ppo(gate=None, trust_region=2.0, fade=None))
    logged = model.logger.name_to_value
    assert np.isfinite(logged["train/loss"]) and logged["train/approx_kl"] >= 0


@pytest.mark.parametrize(
    ("extra", "match"),
    [
        ({"esa_control": "random"}, "expected esa_control None or one of"),
        ({"esa_control": "esc"}, "expected esa_control None or one of"),
        ({"esa": {"fade": 2.0}}, "fade"),
        ({"esa": {"critic": "qnet"}}, "unknown EsaConfig field"),
    ],
)
def test_bad_esa_arguments_are_refused(extra, match):
    env = make_vec_env("InvertedPendulum-v5", n_envs=1, seed=0)
    with pytest.raises(ValueError, match=match):
        ESAPPO("MlpPolicy", env, **extra)


def test_dict_observations_are_refused_with_the_alternative():
    import gymnasium as gym

    class DictObs(gym.ObservationWrapper):
        def __init__(self, env):
            super().__init__(env)
            self.observation_space = spaces.Dict({"x": env.observation_space})

        def observation(self, observation):
            return {"x": observation}

    env = DictObs(gym.make("InvertedPendulum-v5"))
    with pytest.raises(ValueError, match="expected array observations.*FlattenObservation"):
        ESAPPO("MultiInputPolicy", env)
    flat = gym.wrappers.FlattenObservation(env)
    ESAPPO("MlpPolicy", flat, n_steps=64, batch_size=64).learn(128)


def test_the_quadratic_head_saves_and_loads(tmp_path):
    # No fade: with one, two rollouts end the fade at the first fit, which is then skipped.
    model = ppo(ESAPPO, esa=EsaConfig.ppo(gate=None, fade=None), rollouts=2)
    model.save(tmp_path / "model")
    loaded = ESAPPO.load(tmp_path / "model")
    assert isinstance(loaded.esa_head, QuadraticHead)
    for mine, theirs in zip(
        model.esa_head.state_dict().values(), loaded.esa_head.state_dict().values(), strict=True
    ):
        assert th.equal(mine, theirs)
    assert loaded._esa_head_fitted and loaded.esa == model.esa


def test_the_placebo_follows_a_new_env_with_another_number_of_envs(tmp_path):
    model = ppo(ESAPPO, esa=EsaConfig.ppo(gate=None), esa_control="placebo", rollouts=3)
    model.save(tmp_path / "model")
    model.set_env(make_vec_env("InvertedPendulum-v5", n_envs=2, seed=4))
    assert model._esa_control_shift is None  # the placebo's signs went with the sessions
    env = make_vec_env("InvertedPendulum-v5", n_envs=3, seed=4)
    loaded = ESAPPO.load(tmp_path / "model", env=env)
    loaded.learn(3 * 128 * 3)
    assert loaded._esa_control_shift.directions.signs.shape == (3, 1)


class ObservationsOf(gym.Env):
    """An env of any observation space, a 2-D Box action, rewards for actions near 0.3."""

    def __init__(self, space: spaces.Space) -> None:
        self.observation_space = space
        self.action_space = spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
        self.metadata = {"render_fps": 20}
        self._t = 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self._t = 0
        return self.observation_space.sample(), {}

    def step(self, action):
        self._t += 1
        reward = -float(np.sum((np.asarray(action) - 0.3) ** 2))
        return self.observation_space.sample(), reward, False, self._t >= 20, {}


@pytest.mark.parametrize(
    ("space", "policy"),
    [
        (spaces.Box(-1.0, 1.0, shape=(3,)), "MlpPolicy"),
        (spaces.Discrete(5), "MlpPolicy"),
        (spaces.MultiDiscrete([3, 2]), "MlpPolicy"),
        (spaces.MultiBinary(4), "MlpPolicy"),
        (spaces.Box(0, 255, shape=(36, 36, 1), dtype=np.uint8), "CnnPolicy"),
    ],
    ids=["box", "discrete", "multidiscrete", "multibinary", "image"],
)
def test_every_array_observation_space_of_ppo_trains(space, policy):
    model = ESAPPO(
        policy,
        ObservationsOf(space),
        esa=EsaConfig.ppo(gate=None),
        n_steps=64,
        batch_size=32,
        n_epochs=1,
        seed=0,
    )
    model.learn(3 * 64)
    assert model._esa_steps > 0, "ESA shifted actions"
