"""ESAPPO's advantage head as a critic of ``SessionBatch.step`` (``EsaRuntime.step_head``).

On the in-process engine the head's inputs, the step of its linear critic, the batch's step
bookkeeping, the statistics and the executed actions are one call (``Engine.step_head``).
It must give the bits of the same parts called one by one (the path every other engine, and
a faded step, takes): the shifts, the executed actions, the sessions' states and the
statistics; it must refuse bad inputs and change nothing.
"""

import numpy as np
import pytest
import torch as th

from esa_client import EsaClient, EsaConfig, LinearCritic
from esa_client._native import StepStats
from esa_client.common.advantage_head import AdvantageHead
from esa_client.common.runtime import EsaRuntime
from esa_client.errors import InvalidArgument
from esa_client.transports.base import HeadStep

N, D, F = 3, 2, 5


@pytest.fixture
def head():
    with th.random.fork_rng(devices=[]):
        th.manual_seed(5)
        network = AdvantageHead(F, D, hidden=16)
    return network.snapshot(np.array([0.5, 0.0]), np.array([2.0, 0.25], dtype=np.float32))


def runtime(esa: EsaConfig) -> EsaRuntime:
    config = esa.session_config(D, 0.05)
    ones = np.ones(D)
    return EsaRuntime.on_client(esa, EsaClient.in_process(), config, N, -ones, ones)


def step_data(rng: np.random.Generator):
    features = rng.normal(size=(N, F))
    sample, mean = rng.normal(size=(2, N, D)).astype(np.float32)
    std = rng.uniform(0.05, 1.0, size=(N, D)).astype(np.float32)
    return features, sample, mean, std, rng.random(N) < 0.1


def head_step(head, rng: np.random.Generator) -> tuple[np.ndarray, HeadStep, np.ndarray]:
    features, sample, mean, std, starts = step_data(rng)
    return sample, HeadStep(head, features, mean, std), starts


def by_parts(rt: EsaRuntime, head, features, sample, mean, std, starts, strength=1.0):
    """The generic path: the head's inputs, the runtime's step, the shift and executed action."""
    scaled, gain, offset, units = head.step_inputs(features, sample, mean, std)
    applied = rt.step(scaled, starts, LinearCritic(gain, offset), units, strength=strength)
    shift = head.shift(scaled, applied)
    return shift, head.executed(sample, shift)


@pytest.mark.parametrize("paired", [False, True])
@pytest.mark.parametrize("use_policy_std", [False, True])
def test_the_head_step_is_its_parts_bit_for_bit(head, paired, use_policy_std):
    esa = EsaConfig(
        learning_rate=0.5, paired_response=paired, use_policy_std=use_policy_std, gate=None
    )
    fused, parts = runtime(esa), runtime(esa)
    rng = np.random.default_rng(int(paired) + 2 * int(use_policy_std))
    moved = 0.0
    for _ in range(60):
        features, sample, mean, std, starts = step_data(rng)
        step = HeadStep(head, features, mean, std, use_policy_std)
        shift, executed = fused.step_head(sample, step, starts)
        want_shift, want_executed = by_parts(parts, head, features, sample, mean, std, starts)
        assert executed.dtype == np.float32
        np.testing.assert_array_equal(shift, want_shift)
        np.testing.assert_array_equal(executed, want_executed)
        moved += float(np.abs(shift).sum())
    assert moved > 0, "ESA moved the actions"
    np.testing.assert_array_equal(fused.batch.steps, parts.batch.steps)
    for got, want in zip(fused.batch.states(), parts.batch.states(), strict=True):
        assert (got.step, got.episodes_completed, got.probe_pending) == (
            want.step,
            want.episodes_completed,
            want.probe_pending,
        )
        np.testing.assert_array_equal(got.shift, want.shift)
    # The improvement is summed in another order (the critic's offsets cancel): not the bits.
    assert fused._stats.means() == pytest.approx(parts._stats.means(), rel=1e-12, abs=1e-15)
    fused.close()
    parts.close()


def test_a_faded_head_step_is_its_parts(head):
    """Below full strength the step runs in parts: the scales are ``f`` times the std's."""
    esa = EsaConfig(learning_rate=0.5, gate=None)
    faded, parts = runtime(esa), runtime(esa)
    rng = np.random.default_rng(3)
    for t in range(30):
        features, sample, mean, std, starts = step_data(rng)
        strength = 0.25 + 0.5 * (t % 3) / 2
        step = HeadStep(head, features, mean, std, True, strength)
        shift, executed = faded.step_head(sample, step, starts)
        want = by_parts(parts, head, features, sample, mean, std, starts, strength)
        np.testing.assert_array_equal(shift, want[0])
        np.testing.assert_array_equal(executed, want[1])
    assert faded._stats.means() == pytest.approx(parts._stats.means(), rel=1e-12, abs=1e-15)
    # Strength 0: the samples, no session step.
    features, sample, mean, std, starts = step_data(rng)
    steps = faded.batch.steps
    shift, executed = faded.step_head(
        sample, HeadStep(head, features, mean, std, True, 0.0), starts
    )
    np.testing.assert_array_equal(faded.batch.steps, steps)
    np.testing.assert_array_equal(
        shift, head.shift(*[head.step_inputs(features, sample, mean, std)[0]] * 2)
    )
    faded.close()
    parts.close()


@pytest.mark.parametrize("use_stream", [False, True])
def test_a_server_batch_steps_the_head_by_parts(client, head, use_stream):
    """Elsewhere :meth:`SessionBatch.step` of a HeadStep is the head's inputs and its linear
    critic's step (sent ahead on a stream); the statistics go to ``stats`` all the same."""
    esa = EsaConfig(learning_rate=0.5, paired_response=True, gate=None)
    config = esa.session_config(D, 0.05)
    ones = np.ones(D)
    local = EsaClient.in_process()
    with (
        client.create_batch(config, N, use_stream=use_stream) as remote,
        local.create_batch(config, N) as fused,
    ):
        remote_stats, fused_stats = StepStats(-ones, ones), StepStats(-ones, ones)
        rng = np.random.default_rng(11)
        for t in range(40):
            sample, step, starts = head_step(head, rng)
            got = remote.step(
                sample, step, starts, paired=True, stats=remote_stats, improvement=t % 2 == 0
            )
            want = fused.step(
                sample, step, starts, paired=True, stats=fused_stats, improvement=t % 2 == 0
            )
            np.testing.assert_allclose(got[0], want[0], rtol=1e-12, atol=1e-15)
            np.testing.assert_array_equal(got[1], want[1])
        assert remote_stats.means() == pytest.approx(fused_stats.means(), rel=1e-9, abs=1e-12)
        with pytest.raises(ValueError, match="expected no action_scales with a HeadStep"):
            remote.step(sample, step, starts, action_scales=1.0)
    local.close()


def test_a_refused_head_step_changes_nothing(head):
    rt = runtime(EsaConfig(learning_rate=0.5, gate=None))
    rng = np.random.default_rng(7)
    for _ in range(5):
        rt.step_head(*head_step(head, rng))
    before = (rt.batch.steps, rt.batch.states(), rt._stats.means())
    sample, step, starts = head_step(head, rng)
    nan_std = step.std.copy()
    nan_std[1, 0] = np.nan
    with pytest.raises(InvalidArgument, match="critic_gains: expected finite values"):
        rt.step_head(sample, step._replace(std=nan_std), starts)
    with pytest.raises(ValueError, match="features: expected 5 columns"):
        rt.step_head(sample, step._replace(features=step.features[:, :4]), starts)
    with pytest.raises(ValueError, match="expected 3 rows of features and actions"):
        short = HeadStep(head, step.features[:2], step.mean[:2], step.std[:2])
        rt.step_head(sample[:2], short, starts)
    with pytest.raises(ValueError, match=r"\(and 3 episode_starts\), got 3, 3, 3 and 2"):
        rt.step_head(sample, step, starts[:2])
    after = (rt.batch.steps, rt.batch.states(), rt._stats.means())
    np.testing.assert_array_equal(after[0], before[0])
    for got, want in zip(after[1], before[1], strict=True):
        assert (got.step, got.probe_pending) == (want.step, want.probe_pending)
        np.testing.assert_array_equal(got.shift, want.shift)
    assert after[2] == before[2]
    rt.close()
