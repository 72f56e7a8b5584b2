"""The server agrees with reference_law to 1e-9 on random configs and scripts.

Every path is covered: unary Probe/Report, ProbeBatch/ReportBatch and StepStream,
with episode starts, explicit episode ends, resets, retries, decay and pass-through.
"""

import uuid

import numpy as np
import pytest
from reference_law import ReferenceBatch, ReferenceSession

from esa_client import EsaError, InvalidArgument, StepMismatch

TOL = dict(rtol=1e-9, atol=1e-9)


def q_of(rng, probes):
    """A smooth bounded objective plus noise, so the shift moves but cannot run away."""
    target = np.linspace(-0.5, 0.5, probes.shape[-1])
    distance = np.sum((probes - target) ** 2, axis=-1)
    return -10 * np.tanh(distance) + rng.normal(size=probes.shape[:-1])


@pytest.mark.parametrize("seed", range(6))
def test_unary_session_matches_reference(client, make_config, seed, assert_same_states):
    rng = np.random.default_rng(seed)
    config = make_config(rng)
    server = client.create_session(config, f"parity-unary-{seed}-{uuid.uuid4()}")
    reference = ReferenceSession(config)
    for episode in range(5):
        for t in range(int(rng.integers(5, 40))):
            action = rng.normal(size=config.action_dim)
            start = t == 0 and rng.random() < 0.8
            probe = server.probe(action, episode_start=start)
            np.testing.assert_allclose(probe, reference.probe(action, episode_start=start), **TOL)
            if rng.random() < 0.2:  # probe retry with another action replaces the pending one
                action = rng.normal(size=config.action_dim)
                probe = server.probe(action, step=server.step)
                np.testing.assert_allclose(probe, reference.probe(action), **TOL)
            q = float(q_of(rng, probe))
            improved = server.report(q)
            np.testing.assert_allclose(improved, reference.report(q), **TOL)
            if rng.random() < 0.2:  # report retry of the step just applied
                again = server.report(q, step=server.step - 1)
                np.testing.assert_array_equal(again, improved)
                reference.report(q, step=reference.step - 1)
        if episode % 2 == 1:
            assert server.end_episode() == reference.end_episode()
        assert_same_states([server.state()], [reference.state()])
    server.close()


@pytest.mark.parametrize("use_stream", [False, True], ids=["batch", "stream"])
@pytest.mark.parametrize("seed", range(4))
def test_session_batch_matches_reference(client, make_config, seed, use_stream, assert_same_states):
    rng = np.random.default_rng(100 + seed)
    n, d = int(rng.integers(1, 9)), int(rng.integers(1, 4))
    configs = [make_config(rng, d) for _ in range(n)]
    server = client.create_batch(configs, use_stream=use_stream)
    reference = ReferenceBatch(configs)
    for step in range(150):
        actions = rng.normal(size=(n, d))
        starts = rng.random(n) < (1.0 if step == 0 else 0.05)
        if rng.random() < 0.05:
            reset = rng.choice(n, size=int(rng.integers(1, n + 1)), replace=False)
            server.reset(reset)
            reference.reset(reset)
        probes = server.probe(actions, starts)
        np.testing.assert_allclose(probes, reference.probe(actions, starts), **TOL)
        q = q_of(rng, probes)
        improved = server.report(q)
        np.testing.assert_allclose(improved, reference.report(q), **TOL)
        if rng.random() < 0.1:
            again = server.report(q, steps=server.steps - 1)
            np.testing.assert_array_equal(again, improved)
        if rng.random() < 0.05:
            ended = rng.choice(n, size=int(rng.integers(1, n + 1)), replace=False)
            np.testing.assert_array_equal(server.end_episode(ended), reference.end_episode(ended))
        np.testing.assert_array_equal(server.steps, reference.steps)
    assert_same_states(server.states(), reference.states())
    server.close()


@pytest.mark.parametrize("use_stream", [False, True], ids=["batch", "stream"])
def test_rejected_batches_change_nothing_on_either_side(
    client, make_config, use_stream, assert_same_states
):
    rng = np.random.default_rng(7)
    configs = [make_config(rng, 2) for _ in range(3)]
    server = client.create_batch(configs, use_stream=use_stream)
    reference = ReferenceBatch(configs)
    actions = rng.normal(size=(3, 2))
    server.probe(actions, [True] * 3)
    reference.probe(actions, [True] * 3)
    bad_actions = actions.copy()
    bad_actions[2, 1] = np.nan
    cases = [
        (lambda b: b.probe(bad_actions), InvalidArgument),
        (lambda b: b.report([1.0, np.inf, 0.0]), InvalidArgument),
        (lambda b: b.report([1.0, 2.0, 3.0], steps=[0, 1, 0]), StepMismatch),
        (lambda b: b.probe(actions, steps=[0, 0, 3]), StepMismatch),
    ]
    for operation, error in cases:
        for side in (server, reference):
            with pytest.raises(error):
                operation(side)
        assert_same_states(server.states(), reference.states())
    q = q_of(rng, actions)
    np.testing.assert_allclose(server.report(q), reference.report(q), **TOL)
    server.close()
    with pytest.raises(EsaError):
        server.states()
