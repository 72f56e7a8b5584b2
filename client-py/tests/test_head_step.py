"""ESAPPO's step for its advantage head in one native call (``EsaRuntime.step_head``).

On the in-process engine the head's inputs, the step of its linear critic, the batch's step
bookkeeping, the statistics and the executed actions are one call (``Engine.step_head``).
It must give the bits of the same parts called one by one (the path every other engine
takes): the shifts, the executed actions, the sessions' states and the statistics; it must
refuse bad inputs and change nothing; and only an in-process batch runs it.
"""

import numpy as np
import pytest
import torch as th

from esa_client import EsaClient, EsaConfig, LinearCritic
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


def head_step(head, rng: np.random.Generator) -> tuple[HeadStep, np.ndarray]:
    *data, starts = step_data(rng)
    return HeadStep(head, *data), starts


def by_parts(rt: EsaRuntime, head, features, sample, mean, std, starts):
    """The generic path: the head's inputs, the runtime's step, the shift and executed action."""
    scaled, gain, offset, units = head.step_inputs(features, sample, mean, std)
    applied = rt.step(scaled, starts, LinearCritic(gain, offset), units)
    shift = head.shift(scaled, applied)
    return shift, head.executed(sample, shift)


@pytest.mark.parametrize("paired", [False, True])
@pytest.mark.parametrize("use_policy_std", [False, True])
def test_the_head_step_is_its_parts_bit_for_bit(head, paired, use_policy_std):
    esa = EsaConfig(
        learning_rate=0.5, paired_response=paired, use_policy_std=use_policy_std, gate=None
    )
    fused, parts = runtime(esa), runtime(esa)
    assert fused.batch.steps_heads
    rng = np.random.default_rng(int(paired) + 2 * int(use_policy_std))
    moved = 0.0
    for _ in range(60):
        data = step_data(rng)
        shift, executed = fused.step_head(HeadStep(head, *data[:-1]), data[-1])
        want_shift, want_executed = by_parts(parts, head, *data)
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


def test_a_refused_head_step_changes_nothing(head):
    rt = runtime(EsaConfig(learning_rate=0.5, gate=None))
    rng = np.random.default_rng(7)
    for _ in range(5):
        rt.step_head(*head_step(head, rng))
    before = (rt.batch.steps, rt.batch.states(), rt._stats.means())
    step, starts = head_step(head, rng)
    nan_std = step.std.copy()
    nan_std[1, 0] = np.nan
    with pytest.raises(InvalidArgument, match="critic_gains: expected finite values"):
        rt.step_head(step._replace(std=nan_std), starts)
    with pytest.raises(ValueError, match="features: expected 5 columns"):
        rt.step_head(step._replace(features=step.features[:, :4]), starts)
    with pytest.raises(ValueError, match="expected 3 rows of features and actions"):
        rt.step_head(HeadStep(head, *(array[:2] for array in step[1:])), starts)
    with pytest.raises(ValueError, match=r"\(and 3 episode_starts\), got 3, 3, 3 and 2"):
        rt.step_head(step, starts[:2])
    after = (rt.batch.steps, rt.batch.states(), rt._stats.means())
    np.testing.assert_array_equal(after[0], before[0])
    for got, want in zip(after[1], before[1], strict=True):
        assert (got.step, got.probe_pending) == (want.step, want.probe_pending)
        np.testing.assert_array_equal(got.shift, want.shift)
    assert after[2] == before[2]
    rt.close()


def test_only_an_in_process_batch_runs_the_head_step(client, head):
    esa = EsaConfig(gate=None)
    with client.create_batch(esa.session_config(D, 0.05), N) as batch:
        assert not batch.steps_heads
        step, starts = head_step(head, np.random.default_rng(0))
        with pytest.raises(ValueError, match="expected a batch on the in-process engine"):
            batch.step_head(
                step, starts, use_policy_std=True, paired=False, stats=None, improvement=False
            )
