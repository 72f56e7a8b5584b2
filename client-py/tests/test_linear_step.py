"""A step with a critic linear in the action, in one engine call: the law of probe + report.

``Engine.step_linear`` scores the probes with ``Q_i(a) = gain_i . a + offset_i`` inside the
engine. It must do exactly what ProbeBatch, then ReportBatch of the same values do (bit for
bit, against a second engine driven with the two calls and the critic evaluated in Python),
refuse a bad critic with INVALID_ARGUMENT and change nothing, and ``SessionBatch.step``
must give the same actions on the in-process engine as through a real esa-server, where it
falls back to the two calls.
"""

import functools

import numpy as np
import pytest

from esa_client import EsaClient, LinearCritic, SessionConfig
from esa_client._native import INVALID_ARGUMENT, Engine, EngineError


def config_bytes(config: SessionConfig) -> bytes:
    return config.to_proto().SerializeToString()


def linear_q(gain: np.ndarray, offset: np.ndarray, points: np.ndarray, dims) -> np.ndarray:
    """The critic item by item, summed in order from -0.0 as Rust's ``Iterator::sum`` does."""
    values, start = [], 0
    for d, b in zip(dims, offset, strict=True):
        products = gain[start : start + d] * points[start : start + d]
        values.append(functools.reduce(lambda s, x: s + x, products, -0.0) + b)
        start += d
    return np.array(values)


class Engines:
    """The same sessions in two engines: one stepped by step_closed_form, one by probe + report."""

    def __init__(self, configs):
        self.fused, self.split = Engine(), Engine()
        self.dims = [c.action_dim for c in configs]
        self.ids = [f"linear-{i}" for i in range(len(configs))]
        for engine in (self.fused, self.split):
            for session_id, config in zip(self.ids, configs, strict=True):
                engine.create_session(session_id, config_bytes(config))
        self.handles = (self.fused.resolve(self.ids), self.split.resolve(self.ids))

    def states(self, engine: Engine) -> list[bytes]:
        return [engine.get_session(session_id) for session_id in self.ids]

    def step_linear(self, steps, actions, starts, scales, gain, offset, paired):
        tracked = np.asarray(steps, np.int64)  # advanced in place when applied: a copy
        return self.fused.step_closed_form(
            self.handles[0], tracked, actions, starts, scales, gain, offset, paired
        )


def bits(values) -> np.ndarray:
    return np.ascontiguousarray(values, dtype=np.float64).ravel().view(np.uint64)


@pytest.mark.parametrize("seed", range(6))
def test_step_linear_is_probe_then_report_bit_for_bit(make_config, seed):
    rng = np.random.default_rng(7000 + seed)
    n = int(rng.integers(1, 5))
    configs = [make_config(rng) for _ in range(n)]
    pair = Engines(configs)
    steps = np.zeros(n, dtype=np.uint64)
    total = sum(pair.dims)
    for t in range(40):
        starts = (rng.random(n) < 0.1) | (t == 0)
        steps = np.where(starts, 0, steps).astype(np.uint64)
        actions = rng.normal(size=total)
        scales = rng.uniform(0.1, 2.0, size=total) if rng.random() < 0.5 else None
        gain, offset = rng.normal(size=total), rng.normal(size=n)
        paired = bool(rng.random() < 0.5)
        probes, applied = pair.step_linear(steps, actions, starts, scales, gain, offset, paired)
        want = pair.split.probe(pair.handles[1], steps, actions, starts, scales)
        np.testing.assert_array_equal(bits(probes), bits(want[0]))
        np.testing.assert_array_equal(bits(applied), bits(want[1]))
        q = linear_q(gain, offset, np.ravel(want[0]), pair.dims)
        reference = linear_q(gain, offset, np.ravel(want[1]), pair.dims) if paired else None
        pair.split.report(pair.handles[1], steps, q, reference)
        assert pair.states(pair.fused) == pair.states(pair.split)
        steps = steps + 1


def test_bad_critics_are_refused_and_change_nothing():
    config = SessionConfig(action_dim=2, dt=0.05, amplitude=0.1, frequency=10.0, learning_rate=1.0)
    pair = Engines([config, config])
    steps, actions, starts = np.zeros(2, np.uint64), np.zeros(4), np.array([True, True])
    gain, offset = np.ones(4), np.zeros(2)
    before = pair.states(pair.fused)
    nan_gain, inf_offset = gain.copy(), offset.copy()
    nan_gain[3], inf_offset[1] = np.nan, np.inf
    # Finite, but the critic's value at the probes overflows: refused by the report, after
    # the probe, which must be undone.
    overflow = np.full(4, 1e308)
    cases = [
        (gain[:3], offset, "critic_gains: expected 4 values, got 3"),
        (gain, np.zeros(3), "critic_offsets: expected 2 values, got 3"),
        (nan_gain, offset, "critic_gains: expected finite values, got NaN"),
        (gain, inf_offset, "critic_offsets: expected finite values, got inf"),
        (
            overflow,
            np.full(2, 1e308),
            "item 0: invalid argument: q_value: expected a finite number, got inf",
        ),
    ]
    for bad_gain, bad_offset, message in cases:
        for paired in (False, True):
            with pytest.raises(EngineError) as refused:
                pair.step_linear(steps, actions + 1.0, starts, None, bad_gain, bad_offset, paired)
            assert refused.value.code == INVALID_ARGUMENT
            assert refused.value.message == message
            assert pair.states(pair.fused) == before
    # Nothing moved: the same step goes through now.
    pair.step_linear(steps, actions, starts, None, gain, offset, True)
    assert pair.states(pair.fused) != before


def run_batch(batch, rng_seed: int, steps: int = 25):
    rng = np.random.default_rng(rng_seed)
    applied_all = []
    for t in range(steps):
        actions = rng.normal(size=(batch.n, batch.action_dim))
        critic = LinearCritic(rng.normal(size=actions.shape), rng.normal(size=batch.n))
        starts = (rng.random(batch.n) < 0.1) | (t == 0)
        scales = rng.uniform(0.2, 1.0, size=actions.shape)
        _, applied = batch.step(actions, critic, starts, action_scales=scales, paired=bool(t % 2))
        applied_all.append(applied)
    batch.flush()
    return np.stack(applied_all), batch.states()


def test_session_batch_step_in_process_is_the_servers(client):
    config = SessionConfig(
        action_dim=3, dt=0.05, amplitude=0.2, frequency=12.0, learning_rate=2.0, trust_region=0.5
    )
    local = EsaClient.in_process()
    try:
        fused = local.create_batch(config, 4)
        remote = client.create_batch(config, 4, use_stream=True)
        got, got_states = run_batch(fused, 11)
        want, want_states = run_batch(remote, 11)
        np.testing.assert_array_equal(bits(got), bits(want))
        for g, w in zip(got_states, want_states, strict=True):
            np.testing.assert_array_equal(bits(g.shift), bits(w.shift))
            assert g.step == w.step
        remote.close()
    finally:
        local.close()


def test_session_batch_step_refuses_a_linear_critic_of_the_wrong_shape():
    config = SessionConfig(action_dim=2, dt=0.05, amplitude=0.1, frequency=10.0, learning_rate=1.0)
    with EsaClient.in_process() as local:
        batch = local.create_batch(config, 3)
        actions = np.zeros((3, 2))
        for critic in (
            LinearCritic(np.zeros((3, 1)), np.zeros(3)),
            LinearCritic(np.zeros((3, 2)), np.zeros(2)),
        ):
            with pytest.raises(ValueError, match="critic: expected gain of shape"):
                batch.step(actions, critic)
            np.testing.assert_array_equal(batch.steps, [0, 0, 0])
        batch.step(actions, LinearCritic(np.zeros((3, 2)), np.zeros(3)))
        np.testing.assert_array_equal(batch.steps, [1, 1, 1])
