"""CONTRACT.md section 1b from Python: Algorithm 1's applied action, action scales, paired
references and deferred (pipelined) reports agree with ``reference_law`` over unary
calls, ProbeBatch/ReportBatch, the StepStream, Zenoh and Zenoh shards; bad values raise
``InvalidArgument`` and change nothing.
"""

import uuid

import numpy as np
import pytest
from reference_law import ReferenceBatch, ReferenceSession

from esa_client import EsaClient, InvalidArgument, SessionConfig

TOL = dict(rtol=1e-9, atol=1e-9)


def landscape(points, level):
    """Smooth, bounded Q with a level that moves with the state."""
    target = np.linspace(-0.3, 0.3, points.shape[-1])
    return level - np.sum(np.tanh((points - target) ** 2), axis=-1)


@pytest.mark.parametrize("seed", range(4))
def test_unary_session_matches_reference(client, make_config, seed, assert_same_states):
    rng = np.random.default_rng(1000 + seed)
    config = make_config(rng)
    server = client.create_session(config, f"1b-unary-{seed}-{uuid.uuid4()}")
    reference = ReferenceSession(config)
    for _episode in range(4):
        for t in range(int(rng.integers(10, 40))):
            action = rng.normal(size=config.action_dim)
            scale = rng.uniform(0.05, 2.0, size=config.action_dim) if rng.random() < 0.7 else None
            start = t == 0
            probe, applied = server.probe_applied(action, episode_start=start, action_scale=scale)
            want_probe, want_applied = reference.probe_applied(
                action, episode_start=start, action_scale=scale
            )
            np.testing.assert_allclose(probe, want_probe, **TOL)
            np.testing.assert_allclose(applied, want_applied, **TOL)
            level = rng.uniform(-3, 3)
            q = float(landscape(probe, level))
            q_ref = float(landscape(applied, level)) if rng.random() < 0.5 else None
            improved = server.report(q, q_reference=q_ref)
            np.testing.assert_allclose(improved, reference.report(q, q_reference=q_ref), **TOL)
        assert_same_states([server.state()], [reference.state()])
    server.close()


def run_batch(batch, rng, n, d, steps, defer):
    """Drives a batch like a trainer applying Algorithm 1's action; returns every answer."""
    out = []
    for t in range(steps):
        actions = rng.normal(size=(n, d))
        starts = rng.random(n) < (1.0 if t == 0 else 0.03)
        scales = rng.uniform(0.05, 2.0, size=(n, d)) if t % 3 else None
        probes, applied = batch.probe_applied(actions, starts, action_scales=scales)
        out += [probes, applied]
        level = rng.uniform(-3, 3, size=n)
        q = landscape(probes, level)
        q_ref = landscape(applied, level) if t % 2 else None
        improved = batch.report(q, q_references=q_ref, defer=defer)
        if not defer:
            out.append(improved)
    batch.flush()
    return out


@pytest.mark.parametrize("defer", [False, True], ids=["sequential", "pipelined"])
@pytest.mark.parametrize("use_stream", [False, True], ids=["batch", "stream"])
def test_session_batch_matches_reference(
    client, make_config, use_stream, defer, assert_same_states
):
    rng = np.random.default_rng(2000)
    n, d = 5, 3
    configs = [make_config(rng, d) for _ in range(n)]
    server = client.create_batch(configs, use_stream=use_stream)
    reference = ReferenceBatch(configs)
    got = run_batch(server, np.random.default_rng(1), n, d, 120, defer)
    want = run_batch(reference, np.random.default_rng(1), n, d, 120, defer)
    for a, b in zip(got, want, strict=True):
        np.testing.assert_allclose(a, b, **TOL)
    assert_same_states(server.states(), reference.states())
    server.close()


def test_pipelined_and_sequential_steps_answer_the_same(client, make_config, assert_same_states):
    rng = np.random.default_rng(3000)
    configs = [make_config(rng, 2) for _ in range(4)]
    sequential = client.create_batch(configs, use_stream=True)
    pipelined = client.create_batch(configs, use_stream=True)
    a = run_batch(sequential, np.random.default_rng(5), 4, 2, 80, defer=False)
    b = run_batch(pipelined, np.random.default_rng(5), 4, 2, 80, defer=True)
    # Same probes and applied actions (the sequential run also has the report answers).
    sequential_probes = [x for i, x in enumerate(a) if i % 3 != 2]
    for x, y in zip(sequential_probes, b, strict=True):
        np.testing.assert_array_equal(x, y)
    assert_same_states(sequential.states(), pipelined.states())
    sequential.close()
    pipelined.close()


@pytest.mark.parametrize("use_stream", [False, True], ids=["batch", "stream"])
def test_a_failed_deferred_report_raises_changes_nothing_and_can_be_replaced(client, use_stream):
    config = SessionConfig(action_dim=1, dt=0.05, amplitude=0.2, frequency=10.0, learning_rate=0.1)
    batch = client.create_batch(config, n=2, use_stream=use_stream)
    batch.probe_applied(np.zeros((2, 1)), [True, True])
    batch.report([1.0, np.nan], defer=True)
    for _ in range(2):  # retrying the probe retries the bad report too
        with pytest.raises(InvalidArgument, match="q_value"):
            batch.probe_applied(np.zeros((2, 1)))
        states = [client.session_state(i) for i in batch.ids]
        assert [(s.step, s.probe_pending) for s in states] == [(0, True), (0, True)]
    batch.report([1.0, 2.0], defer=True)  # replaces the pending report of step 0
    probes, applied = batch.probe_applied(np.zeros((2, 1)))
    assert probes.shape == applied.shape == (2, 1)
    assert [(s.step, s.probe_pending) for s in batch.states()] == [(1, True), (1, True)]
    batch.close()


def good_config(**fields):
    return SessionConfig(
        action_dim=2, dt=0.01, amplitude=0.2, frequency=60.0, learning_rate=0.25, **fields
    )


@pytest.mark.parametrize(
    "field, value",
    [
        ("response_rms_rate", 0.0),
        ("response_rms_rate", 1.5),
        ("response_rms_rate", float("nan")),
        ("response_clip", 0.0),
        ("response_clip", -1.0),
        ("response_clip", float("inf")),
        ("shift_leak", 1.0),
        ("shift_leak", -0.1),
        ("shift_leak", float("nan")),
        ("trust_region", 0.0),
        ("trust_region", float("inf")),
        ("normalize_response", "yes"),
    ],
)
def test_bad_section_1b_config_values_fail_early_and_on_the_server(client, field, value):
    with pytest.raises(ValueError, match=field):
        good_config(**{field: value})
    if field == "normalize_response":
        return
    message = good_config().to_proto()
    setattr(message, field, value)
    with pytest.raises(InvalidArgument, match=field):
        client.create_session(message, f"bad-{field}-{uuid.uuid4()}")


def test_config_round_trips_the_section_1b_fields(client):
    config = good_config(
        normalize_response=True,
        response_rms_rate=0.1,
        response_clip=2.0,
        shift_leak=0.0,
        trust_region=1.5,
    )
    session = client.create_session(config)
    assert session.state().config == config
    assert SessionConfig.from_proto(config.to_proto()) == config
    session.close()


@pytest.mark.parametrize("use_stream", [False, True], ids=["batch", "stream"])
def test_bad_scales_and_references_are_refused_and_change_nothing(
    client, use_stream, assert_same_states
):
    config = good_config(normalize_response=True, trust_region=1.0)
    batch = client.create_batch(config, n=3, use_stream=use_stream)
    reference = ReferenceBatch([config] * 3)
    actions = np.full((3, 2), 0.1)
    for side in (batch, reference):
        side.probe_applied(actions, [True] * 3)
    bad_scales = np.ones((3, 2))
    bad_scales[2, 1] = 0.0
    cases = [
        lambda b: b.probe_applied(actions, action_scales=bad_scales),
        lambda b: b.probe_applied(actions, action_scales=np.nan),
        lambda b: b.report([1.0, 2.0, 3.0], q_references=[0.0, np.inf, 0.0]),
    ]
    for operation in cases:
        for side in (batch, reference):
            with pytest.raises(InvalidArgument):
                operation(side)
        assert_same_states(batch.states(), reference.states())
    with pytest.raises(ValueError, match="q_references"):
        batch.report([1.0, 2.0, 3.0], q_references=[0.0, 1.0])
    batch.close()


def test_unary_bad_scale_and_reference(client):
    session = client.create_session(good_config())
    with pytest.raises(InvalidArgument, match="action_scale"):
        session.probe_applied([0.0, 0.0], action_scale=[1.0, -1.0])
    with pytest.raises(InvalidArgument, match="action_scale"):
        session.probe_applied([0.0, 0.0], action_scale=[1.0, 1.0, 1.0])
    session.probe([0.0, 0.0], episode_start=True)
    with pytest.raises(InvalidArgument, match="q_reference"):
        session.report(1.0, q_reference=float("nan"))
    assert session.state().probe_pending
    session.close()


def test_zenoh_matches_reference(zenoh_client, make_config, assert_same_states):
    rng = np.random.default_rng(4000)
    configs = [make_config(rng, 2) for _ in range(3)]
    for use_stream in (False, True):
        batch = zenoh_client.create_batch(configs, use_stream=use_stream)
        reference = ReferenceBatch(configs)
        got = run_batch(batch, np.random.default_rng(9), 3, 2, 60, defer=True)
        want = run_batch(reference, np.random.default_rng(9), 3, 2, 60, defer=True)
        for a, b in zip(got, want, strict=True):
            np.testing.assert_allclose(a, b, **TOL)
        assert_same_states(batch.states(), reference.states())
        batch.close()


@pytest.mark.parametrize("use_stream", [False, True], ids=["batch", "stream"])
def test_sharded_batches_split_and_merge_scales_references_and_applied_actions(
    server_bin, use_stream, assert_same_states
):
    from esa_client.sharding import shard_of

    config = good_config(normalize_response=True, shift_leak=0.01, trust_region=1.0)
    ids = [f"1b-shard-{k}" for k in range(6)]
    assert {shard_of(i, 2) for i in ids} == {0, 1}, "ids must span both shards"
    with EsaClient.spawn(server_bin, transport="zenoh", shards=2) as sharded:
        batch = sharded.create_batch(config, 6, ids=ids, use_stream=use_stream)
        reference = ReferenceBatch([config] * 6, ids)
        got = run_batch(batch, np.random.default_rng(3), 6, 2, 40, defer=True)
        want = run_batch(reference, np.random.default_rng(3), 6, 2, 40, defer=True)
        for a, b in zip(got, want, strict=True):
            np.testing.assert_allclose(a, b, **TOL)
        assert_same_states(batch.states(), reference.states())
        batch.close()


@pytest.mark.parametrize("use_stream", [False, True], ids=["batch", "stream"])
def test_a_failed_deferred_report_before_an_episode_start_of_every_session_can_be_replaced(
    client, use_stream
):
    config = SessionConfig(action_dim=1, dt=0.05, amplitude=0.2, frequency=10.0, learning_rate=0.1)
    batch = client.create_batch(config, n=2, use_stream=use_stream)
    batch.probe_applied(np.zeros((2, 1)), [True, True])
    batch.report([np.nan, 1.0], defer=True)
    with pytest.raises(InvalidArgument, match="q_value"):
        batch.probe_applied(np.zeros((2, 1)), [True, True])
    states = [client.session_state(i) for i in batch.ids]
    assert [(s.step, s.episodes_completed) for s in states] == [(0, 0), (0, 0)], "nothing applied"
    batch.report([2.0, 1.0], defer=True)
    batch.probe_applied(np.zeros((2, 1)), [True, True])
    assert [s.episodes_completed for s in batch.states()] == [1, 1]
    batch.close()


def test_the_applied_action_keeps_the_trust_region_of_its_own_probe(client):
    config = good_config(trust_region=1.0, disable_highpass=True)
    session = client.create_session(config)
    reference = ReferenceSession(config)
    for t, (scale, q) in enumerate([(1.0, 1e9), (1.0, -1e9), (0.01, 0.0)]):
        for side in (session, reference):
            _, applied = side.probe_applied([0.0, 0.0], episode_start=t == 0, action_scale=scale)
            assert np.all(np.abs(applied) <= scale), (t, applied)
            side.report(q)
    np.testing.assert_allclose(session.state().shift, reference.state().shift, **TOL)
    session.close()
