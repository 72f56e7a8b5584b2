"""The quadratic critic in closed form (``QuadraticCritic``), evaluated by the engine.

``Q_i(a) = offset_i + sum_j (gain_ij x_j + curvature_ij x_j^2)``, ``x = clip(a, low, high)``:
the in-process engine evaluates it in the step's one call (``Engine.step_quadratic``), every
other transport here at the probes; both give the same bits (at this D). Bad critics are
refused before anything changes. ESAPPO's quadratic head hands the engine its closed form
(esa-core's forward pass on a copy of its weights), equal to the torch head at the clipped action
to float32 rounding.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env

from esa_client import EsaClient, EsaConfig, QuadraticCritic, _native
from esa_client.common.quadratic_head import CriticAtStep, QuadraticHead, Rollout, fit_critic
from esa_client.sb3 import ESAPPO

N, D = 3, 2
LOW, HIGH = np.array([-1.0, -0.5]), np.array([1.0, np.inf])


def critic_at(t: int, bounded: bool = True) -> QuadraticCritic:
    x = float(t)
    gain = np.array([[1.0, -0.5], [0.2 * x, 2.0], [-1.0, 0.3]])
    curvature = -np.array([[0.5, 0.0], [2.0, 0.1 * x], [0.25, 1.0]])
    offset = np.array([x, -3.0, 0.5])
    return QuadraticCritic(gain, curvature, offset, *((LOW, HIGH) if bounded else (None, None)))


def written_out(critic: QuadraticCritic, points: np.ndarray) -> np.ndarray:
    """The critic at ``(k N, D)`` points, one sum at a time."""
    values = []
    for row, point in enumerate(points):
        i = row % N
        total = critic.offset[i]
        for j in range(D):
            x = point[j] if critic.low is None else min(max(point[j], LOW[j]), HIGH[j])
            total += critic.gain[i, j] * x + critic.curvature[i, j] * x * x
        values.append(total)
    return np.array(values)


def test_the_numpy_critic_is_its_closed_form_at_the_clipped_action():
    rng = np.random.default_rng(0)
    for bounded in (True, False):
        critic = critic_at(3, bounded)
        points = rng.normal(scale=2.0, size=(2 * N, D))
        np.testing.assert_allclose(critic(points), written_out(critic, points), rtol=1e-14)
    # Flat past the box: every point beyond a bound scores as the bound.
    critic = critic_at(1)
    far = np.tile([[5.0, -7.0]], (N, 1))
    np.testing.assert_array_equal(critic(far), critic(np.tile([[1.0, -0.5]], (N, 1))))


def run(batch, steps: int, paired: bool) -> list[np.ndarray]:
    rng = np.random.default_rng(4)
    applied_seen = []
    for t in range(steps):
        actions = rng.normal(scale=0.8, size=(N, D))
        starts = rng.random(N) < 0.05
        _, applied = batch.step(actions, critic_at(t), starts, action_scales=0.3, paired=paired)
        applied_seen.append(applied)
    batch.flush()
    return applied_seen


@pytest.mark.parametrize("paired", [False, True])
def test_the_engine_and_the_wire_step_the_same_quadratic_critic(client, paired):
    esa = EsaConfig(learning_rate=0.5, gate=None)
    config = esa.session_config(D, 0.05)
    local = EsaClient.in_process()
    got = {}
    with (
        local.create_batch(config, N) as fused,
        client.create_batch(config, N) as unary,
        client.create_batch(config, N, use_stream=True) as ahead,
    ):
        for name, batch in (("fused", fused), ("unary", unary), ("ahead", ahead)):
            got[name] = (run(batch, 60, paired), [s.shift for s in batch.states()])
    local.close()
    moved = np.abs(np.array(got["fused"][1])).sum()
    assert moved > 0, "ESA moved the shifts"
    for name in ("unary", "ahead"):
        for a, b in zip(got[name][0], got["fused"][0], strict=True):
            np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(got[name][1], got["fused"][1])


def bad_critics() -> list[tuple[QuadraticCritic, str]]:
    good = critic_at(2)
    nan_gain = good.gain.copy()
    nan_gain[1, 0] = np.nan
    inf_offset = good.offset.copy()
    inf_offset[2] = np.inf
    positive = good.curvature.copy()
    positive[0, 1] = 0.5
    return [
        (good._replace(gain=good.gain[:2]), r"expected gain of shape \(3, 2\), curvature of"),
        (good._replace(curvature=good.curvature[:, :1]), r"got .*'curvature': \(3, 1\)"),
        (good._replace(offset=good.offset[:2]), r"offset of shape \(3,\), .*'offset': \(2,\)"),
        (good._replace(gain=nan_gain), "expected a finite gain, got"),
        (good._replace(offset=inf_offset), "expected a finite offset, got"),
        (good._replace(curvature=positive), "expected curvature <= 0, got"),
        (good._replace(high=None), "expected both bounds or neither, got"),
        (
            good._replace(low=LOW[:1]),
            r"low of shape \(2,\), high of shape \(2,\), got .*'low': \(1,\)",
        ),
        (good._replace(low=np.array([2.0, -0.5])), "expected low <= high"),
        (good._replace(low=np.array([np.nan, 0.0])), "expected low <= high"),
    ]


@pytest.mark.parametrize("where", ["in_process", "unary", "ahead"])
def test_a_bad_quadratic_critic_is_refused_and_changes_nothing(client, where):
    config = EsaConfig(learning_rate=0.5, gate=None).session_config(D, 0.05)
    local = EsaClient.in_process()
    owner = local if where == "in_process" else client
    with owner.create_batch(config, N, use_stream=where == "ahead") as batch:
        run(batch, 5, paired=True)
        before = (batch.steps, batch.states())
        actions = np.zeros((N, D))
        for critic, message in bad_critics():
            with pytest.raises(ValueError, match=message):
                batch.step(actions, critic, None, action_scales=0.3, paired=True)
        batch.flush()
        after = (batch.steps, batch.states())
        np.testing.assert_array_equal(after[0], before[0])
        for got, want in zip(after[1], before[1], strict=True):
            assert (got.step, got.probe_pending) == (want.step, want.probe_pending)
            np.testing.assert_array_equal(got.shift, want.shift)
    local.close()


def test_the_engine_refuses_what_the_session_would_have(client):
    """The engine's own checks (for callers of ``Engine.step_closed_form``), all or nothing."""
    from esa_client._native import Engine, EngineError

    engine = Engine()
    config = EsaConfig(gate=None).session_config(D, 0.05).to_proto().SerializeToString()
    ids = [engine.create_session(None, config) for _ in range(N)]
    handle = engine.resolve(ids)
    good = critic_at(0)
    steps, actions, starts = np.zeros(N, np.int64), np.zeros((N, D)), np.zeros(N, bool)

    def step(curvature, low, high, paired=False):
        critic = (good.gain, good.offset, paired, curvature, low, high)
        return engine.step_closed_form(handle, steps.copy(), actions, starts, None, *critic)

    with pytest.raises(EngineError, match="critic_curvatures: expected values <= 0, got"):
        step(-good.curvature, LOW, HIGH)
    with pytest.raises(EngineError, match="critic_bounds: expected low <= high"):
        step(good.curvature, HIGH, LOW)
    with pytest.raises(ValueError, match="expected None for a linear critic"):
        step(None, LOW, HIGH)
    probes, applied = step(good.curvature, LOW, HIGH, paired=True)
    assert probes.shape == applied.shape == (N, D)


def test_esappo_hands_the_engine_the_quadratic_heads_closed_form(monkeypatch):
    """On a short ESAPPO run, the closed form equals the torch head at the clipped action
    (probes near the policy and past the box) to float32 rounding, at every step."""
    closed_form = CriticAtStep.closed_form
    worst, calls = [0.0], [0]
    rng = np.random.default_rng(0)

    def checked(self: CriticAtStep) -> QuadraticCritic:
        critic = closed_form(self)
        assert isinstance(self.critic, QuadraticHead)
        n = len(self.mean)
        spread = rng.normal(scale=2.0, size=(4, n, self.mean.shape[1]))
        points = (self.mean + spread * self.std).reshape(-1, self.mean.shape[1])
        points = np.concatenate([points, np.clip(points, -1.5, 1.5) * 2.0])
        got, want = critic(points), self(points)
        scale = np.abs(want).max() + 1.0
        worst[0] = max(worst[0], float(np.abs(got - want).max() / scale))
        calls[0] += 1
        return critic

    monkeypatch.setattr(CriticAtStep, "closed_form", checked)
    env = make_vec_env("InvertedPendulum-v5", n_envs=2, seed=3)
    model = ESAPPO(
        "MlpPolicy",
        env,
        seed=3,
        n_steps=128,
        batch_size=64,
        n_epochs=2,
        policy_kwargs=dict(net_arch=[32]),
        esa=EsaConfig.ppo(gate=None, fade=None),
    )
    model.learn(3 * 128 * 2)
    model.esa_close()
    assert calls[0] > 100, calls
    assert worst[0] < 1e-6, worst


def head_values(head: QuadraticHead, features: th.Tensor, mean, std, points) -> np.ndarray:
    """The closed form at ``points`` next to the torch head there."""
    gain, curvature, offset = head.closed_form(features, mean, std)
    closed = (gain * points + curvature * points * points).sum(axis=1) + offset
    z = th.as_tensor((points - mean) / std, dtype=th.float32)
    with th.no_grad():
        torch_values = head(features, z).numpy().astype(np.float64)
    return np.abs(closed - torch_values).max() / (np.abs(torch_values).max() + 1.0)


def test_head_closed_form_follows_every_change_of_the_weights():
    """esa-core's copy of the weights follows a fused Adam fit (which bumps no tensor version),
    a state dict loaded in place, and stays with the module's own weights."""
    th.manual_seed(0)
    head, other = QuadraticHead(5, D, hidden=16), QuadraticHead(5, D, hidden=16)
    features = th.randn(N, 5)
    rng = np.random.default_rng(0)
    mean, std = rng.normal(size=(N, D)), rng.uniform(0.2, 1.0, size=(N, D))
    points = mean + rng.normal(size=(N, D)) * std
    assert head_values(head, features, mean, std, points) < 1e-6
    before = head.closed_form(features, mean, std)[0].copy()
    optimizer = th.optim.Adam(head.parameters(), lr=0.1, fused=True)
    rollout = Rollout(features, th.randn(N, D), th.randn(N))
    fit_critic(head, optimizer, [rollout], epochs=3, batch_size=N, rng=rng)
    assert not np.array_equal(head.closed_form(features, mean, std)[0], before)
    assert head_values(head, features, mean, std, points) < 1e-6
    head.load_state_dict(other.state_dict())
    np.testing.assert_array_equal(
        head.closed_form(features, mean, std)[0], other.closed_form(features, mean, std)[0]
    )


def test_native_head_refuses_bad_layers_and_inputs():
    """Layers that do not chain, and inputs of the wrong size, non-finite or with std <= 0."""
    w = np.zeros
    good = [(w((4, 3)), w(4)), (w((4, 4)), w(4)), (w((2 * D, 4)), w(2 * D))]
    with pytest.raises(ValueError, match="expected 3 layers, got 2"):
        _native.QuadraticHead(good[:2])
    with pytest.raises(ValueError, match="layer 1: expected a weight of 4 x 4 values, got 12"):
        _native.QuadraticHead([good[0], (w((4, 3)), w(4)), good[2]])
    with pytest.raises(ValueError, match="expected 2 D outputs"):
        _native.QuadraticHead([good[0], good[1], (w((3, 4)), w(3))])
    head = _native.QuadraticHead(good)
    features, mean, std = np.zeros((N, 3)), np.zeros((N, D)), np.ones((N, D))
    with pytest.raises(ValueError, match=r"expected features of N x 3 values"):
        head.closed_form(np.zeros((N, 4)), mean, std)
    for bad in (np.nan, np.inf):
        with pytest.raises(ValueError, match="expected finite features and mean"):
            head.closed_form(np.full((N, 3), bad), mean, std)
    with pytest.raises(ValueError, match="a finite std > 0"):
        head.closed_form(features, mean, np.zeros((N, D)))
    gain, curvature, offset = head.closed_form(features, mean, std)
    assert gain.shape == curvature.shape == (N, D) and offset.shape == (N,)
