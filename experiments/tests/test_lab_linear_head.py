"""The lab's linear advantage head: the snapshot a rollout step uses, the fit's gradients.

Both replace torch code for speed and must compute the same function: the snapshot's
``w(s)`` and its critic agree with the torch head to float32 precision, the gradients agree
with autograd's, and bad shapes are refused with a ``ValueError``. The snapshot also keeps
its own bits: each layer's sum in order in float32, the C library's tanh.
"""

import numpy as np
import pytest
import torch as th
from esa_client.sb3 import EsaConfig
from torch.nn import functional as F

from esa_experiments.lab.linear_head import AdvantageHead, HeadSnapshot, _c_tanhf, _gradients
from esa_experiments.lab.ppo_arms import esappo_class

LinearESAPPO = esappo_class(critic="linear", objective="clip")


@pytest.fixture
def head() -> AdvantageHead:
    with th.random.fork_rng(devices=[]):
        th.manual_seed(3)
        return AdvantageHead(5, 2, hidden=16)


CENTER, HALF_WIDTH = np.array([0.5, -1.0]), np.array([2.0, 0.25])


def test_the_snapshot_computes_the_torch_heads_w_and_critic(head):
    rng = np.random.default_rng(0)
    features = rng.normal(size=(7, 5)).astype(np.float32)
    mlp = head.snapshot(CENTER, HALF_WIDTH)
    assert (mlp.features_dim, mlp.action_dim) == (5, 2)
    with th.no_grad():
        want = head.weights(th.from_numpy(features)).numpy()
    w = mlp.weights(features)
    np.testing.assert_allclose(w, want, rtol=1e-5, atol=1e-6)
    mean = rng.normal(size=(7, 2)).astype(np.float32)
    std = rng.uniform(0.1, 1.0, size=(7, 2)).astype(np.float32)
    gain, offset = mlp.critic(features, mean, std)
    np.testing.assert_allclose(gain, w * HALF_WIDTH / std, rtol=1e-12)
    np.testing.assert_allclose(offset, (w * (CENTER - mean) / std).sum(axis=1), rtol=1e-12)
    # The critic is the head's advantage of the raw action a = c + h x.
    x = rng.normal(size=(7, 2))
    with th.no_grad():
        z = th.from_numpy(((CENTER + HALF_WIDTH * x - mean) / std).astype(np.float32))
        advantage = head(th.from_numpy(features), z).numpy()
    np.testing.assert_allclose((gain * x).sum(axis=1) + offset, advantage, rtol=1e-4, atol=1e-5)
    # Strided views are read as they are.
    wide = np.repeat(features, 2, axis=1)[:, ::2]
    np.testing.assert_array_equal(mlp.weights(wide), w)


def test_each_layer_sums_its_inputs_in_order_in_float32(head):
    # The snapshot's bits, one value at a time: products and sums in float32, left to
    # right, then the bias; the C library's tanh between layers.
    rng = np.random.default_rng(5)
    features = (rng.normal(size=(3, 5)) * 4).astype(np.float32)
    layers = [
        (layer.weight.detach().numpy(), layer.bias.detach().numpy()) for layer in head._linears
    ]
    tanh = _c_tanhf()
    want = []
    for row in features:
        hidden = list(row)
        for index, (weight, bias) in enumerate(layers):
            out = []
            for weights_row, b in zip(weight, bias, strict=True):
                total = np.float32(-0.0)
                for w, x in zip(weights_row, hidden, strict=True):
                    total = np.float32(total + np.float32(w * x))
                out.append(np.float32(total + b))
            hidden = out if index == len(layers) - 1 else [np.float32(tanh(v)) for v in out]
        want.append(hidden)
    got = head.snapshot(CENTER, HALF_WIDTH).weights(features)
    np.testing.assert_array_equal(got, np.array(want, np.float32).astype(np.float64))


def test_the_step_inputs_are_numpys_units_and_the_critic_bit_for_bit(head):
    rng = np.random.default_rng(1)
    features = rng.normal(size=(4, 5)).astype(np.float32)
    sample, mean = rng.normal(size=(2, 4, 2)).astype(np.float32)
    std = rng.uniform(0.1, 1.0, size=(4, 2)).astype(np.float32)
    mlp = head.snapshot(CENTER, HALF_WIDTH)
    scaled, gain, offset, units = mlp.step_inputs(features, sample, mean, std)
    # The numpy reference: the same float64 operations, so the same bits.
    np.testing.assert_array_equal(scaled, (sample.astype(np.float64) - CENTER) / HALF_WIDTH)
    want_gain, want_offset = mlp.critic(features, mean, std)
    np.testing.assert_array_equal(gain, want_gain)
    np.testing.assert_array_equal(offset, want_offset)
    np.testing.assert_array_equal(units, std / HALF_WIDTH)
    # Columns of one (N, 3 D) array, as torch's views may be.
    packed = np.concatenate([sample, mean, std], axis=1)
    views = (packed[:, :2], packed[:, 2:4], packed[:, 4:])
    want = (scaled, gain, offset, units)
    for got, expected in zip(mlp.step_inputs(features, *views), want, strict=True):
        np.testing.assert_array_equal(got, expected)


@pytest.mark.parametrize("box_dtype", [np.float16, np.float32, np.float64])
def test_the_std_in_esa_units_is_numpys_for_the_boxs_dtype(head, box_dtype):
    # The numpy reference: the float32 std divided by the Box's half-width (in float32 for a
    # float32 or float16 Box), floored at float32's smallest normal.
    half_width = np.array([3.0, 0.1], dtype=box_dtype)
    mlp = head.snapshot(CENTER, half_width)
    rng = np.random.default_rng(4)
    std = (rng.uniform(0.0, 2.0, size=(64, 2)) * 10.0 ** rng.integers(-45, 3, (64, 2))).astype(
        np.float32
    )
    std[:3] = [[0.0, -0.0], [np.nan, np.inf], [1e-45, 1e-38]]
    zeros = np.zeros((64, 2), np.float32)
    got = mlp.step_inputs(np.zeros((64, 5), np.float32), zeros, zeros, std)[3]
    want = np.maximum(std / half_width, float(np.finfo(np.float32).tiny)).astype(np.float64)
    assert got.dtype == np.float64
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("box_dtype", [np.float32, np.float64])
def test_the_shift_is_numpys_bit_for_bit(head, box_dtype):
    # ESAPPO's scaling comes from the Box: float32 bounds give float32 half-widths.
    half_width = HALF_WIDTH.astype(box_dtype)
    mlp = head.snapshot(CENTER, half_width)
    rng = np.random.default_rng(2)
    for _ in range(200):
        sample = rng.normal(size=(4, 2)).astype(np.float32)
        scaled = (sample.astype(np.float64) - CENTER) / half_width
        applied = scaled + rng.normal(size=(4, 2)) * 10.0 ** rng.integers(-9, 1)
        # The numpy reference.
        np.testing.assert_array_equal(mlp.shift(scaled, applied), (applied - scaled) * half_width)


def test_the_shift_refuses_bad_shapes(head):
    mlp = head.snapshot(CENTER, HALF_WIDTH)
    f64 = np.zeros((2, 2))
    with pytest.raises(ValueError, match="applied: expected 2 columns"):
        mlp.shift(f64, np.zeros((2, 3)))
    with pytest.raises(ValueError, match="scaled and applied with as many rows, got 2 and 3"):
        mlp.shift(f64, np.zeros((3, 2)))


@pytest.mark.parametrize("dtype", [th.float64, th.float32, th.uint8])
def test_esappo_reads_a_box_observation_as_sb3_preprocesses_it(dtype):
    model = LinearESAPPO("MlpPolicy", "Pendulum-v1", n_steps=64, seed=0)
    obs = (th.rand(5, 3, dtype=th.float64) * 200).to(dtype)
    want = model._head_features(obs).numpy()
    got = model._step_features(obs)
    # float64 goes to the snapshot as it is; it rounds it as torch's float() does.
    assert got.dtype == (np.float64 if dtype == th.float64 else np.float32)
    np.testing.assert_array_equal(got.astype(np.float32), want)
    mlp = model._esa_mlp()
    np.testing.assert_array_equal(mlp.weights(got), mlp.weights(want))


def test_the_step_inputs_refuse_bad_shapes(head):
    mlp = head.snapshot(CENTER, HALF_WIDTH)
    features, rows = np.zeros((2, 5), np.float32), np.ones((2, 2), np.float32)
    with pytest.raises(ValueError, match="actions: expected 2 columns"):
        mlp.step_inputs(features, np.zeros((2, 3), np.float32), rows, rows)
    with pytest.raises(ValueError, match="expected actions with 2 rows"):
        mlp.step_inputs(features, np.ones((3, 2), np.float32), rows, rows)
    with pytest.raises(ValueError, match="std: expected 2 columns"):
        mlp.step_inputs(features, rows, rows, np.ones((2, 1), np.float32))
    with pytest.raises(ValueError, match="expected mean and std with 2 rows"):
        mlp.step_inputs(features, rows, np.ones((1, 2), np.float32), rows)


def test_the_snapshot_refuses_bad_shapes(head):
    mlp = head.snapshot(CENTER, HALF_WIDTH)
    f32 = np.float32
    with pytest.raises(ValueError, match="features: expected 5 columns"):
        mlp.weights(np.zeros((2, 4), f32))
    with pytest.raises(ValueError, match="mean: expected 2 columns"):
        mlp.critic(np.zeros((2, 5), f32), np.zeros((2, 3), f32), np.ones((2, 2), f32))
    with pytest.raises(ValueError, match="expected mean and std with 2 rows"):
        mlp.critic(np.zeros((2, 5), f32), np.zeros((3, 2), f32), np.ones((3, 2), f32))
    weights = [np.zeros((4, 5), f32), np.zeros((2, 3), f32)]
    with pytest.raises(ValueError, match="layer 1: expected a weight of shape"):
        HeadSnapshot(weights, [np.zeros(4, f32), np.zeros(2, f32)], [0.0, 0.0], [1.0, 1.0])
    layer = [np.zeros((2, 5), f32)], [np.zeros(2, f32)]
    with pytest.raises(ValueError, match="expected as many biases as weights"):
        HeadSnapshot(layer[0], [], [0.0, 0.0], [1.0, 1.0])
    with pytest.raises(ValueError, match="center and half_width of length 2"):
        HeadSnapshot(*layer, [0.0], [1.0])
    with pytest.raises(ValueError, match="half_width > 0"):
        HeadSnapshot(*layer, [0.0, 0.0], [1.0, 0.0])


def test_the_fits_gradients_are_autograds(head):
    rng = np.random.default_rng(1)
    features = th.from_numpy(rng.normal(size=(64, 5)).astype(np.float32))
    z = th.from_numpy(rng.normal(size=(64, 2)).astype(np.float32))
    target = th.from_numpy(rng.normal(size=64).astype(np.float32))
    head.zero_grad()
    want_loss = F.mse_loss(head(features, z), target)
    want_loss.backward()
    with th.no_grad():
        loss, gradients = _gradients(head, features, z, target)
    assert float(loss) == pytest.approx(want_loss.item(), rel=1e-6)
    for parameter, gradient in zip(head.parameters(), gradients, strict=True):
        assert parameter.grad is not None
        np.testing.assert_allclose(gradient, parameter.grad, rtol=1e-4, atol=1e-6)


def test_the_snapshot_follows_every_fit():
    # Fused Adam writes the parameters without bumping their version counters: the snapshot
    # must still be taken again after each fit, or ESA would keep scoring with a stale head.
    model = LinearESAPPO(
        "MlpPolicy",
        "InvertedPendulum-v5",
        esa=EsaConfig(gate=None),
        n_steps=64,
        batch_size=64,
        seed=0,
        device="cpu",
    )
    model.learn(3 * 64)  # three fits; ESA steps with the head of the first two
    assert model.esa_head.fits == 3
    obs = th.as_tensor(model._last_obs)
    with th.no_grad():
        want = model.esa_head.weights(model._head_features(obs)).numpy()
    got = model._esa_mlp().weights(model._step_features(obs))
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
    model.esa_close()
