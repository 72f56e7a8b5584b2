"""``SessionBatch.step`` sent ahead of its answer: the pipelined step, against a real server.

For a linear critic (evaluated by the server) and for any critic (evaluated here, at probes
computed ahead), the applied actions it computes ahead (from the previous answer's shifts, with
esa-core's own functions) are the bits the in-process engine's whole step returns, and so are
the sessions' states; an error of a step surfaces at the next call with nothing of it applied;
bad critic values are refused before anything is sent; a batch that cannot pipeline waits for
its answers with the same bits; the probes computed ahead are the server's.
"""

import numpy as np
import pytest

from esa_client import (
    EsaClient,
    InvalidArgument,
    LinearCritic,
    QuadraticCritic,
    ServerUnavailable,
    SessionConfig,
    StatusCode,
    StepMismatch,
)
from esa_client._native import EngineError, StatusError, StepAhead
from esa_client.transports.grpc import AheadStepper

CONFIG = SessionConfig(
    action_dim=2,
    dt=0.02,
    amplitude=[0.3],
    frequency=[40.0, 25.0],
    learning_rate=[0.5],
    action_low=[-1.0],
    action_high=[1.0],
    shift_limit=0.4,
    normalize_response=True,
    shift_leak=0.01,
    trust_region=1.5,
)
N = 3


@pytest.fixture(scope="module")
def native(server_bin):
    """A private server through the native client (whose StepStream pipelines)."""
    with EsaClient.spawn(server_bin) as client:
        yield client


def script(steps: int, seed: int = 0):
    """Random sampled actions, scales, critics and episode starts, one tuple per step."""
    rng = np.random.default_rng(seed)
    for t in range(steps):
        actions = rng.uniform(-1.5, 1.5, size=(N, 2))
        scales = rng.uniform(0.01, 0.9, size=(N, 2))
        critic = LinearCritic(rng.normal(size=(N, 2)), rng.normal(size=N))
        starts = rng.random(N) < 0.08
        starts[:] |= t == 0
        yield actions, scales, critic, starts


def curved(critic: LinearCritic):
    """A critic that is not linear in the action, built from a linear one's numbers."""

    def q(points):
        # ``points`` are (k n, D): the n states tiled k times.
        reps = len(points) // len(critic.offset)
        centre = np.tile(critic.gain, (reps, 1))
        scale = np.tile(1.0 + critic.offset**2, reps)
        return -scale * ((points - 0.5 * centre) ** 2).sum(axis=1) + np.sin(3.0 * points[:, 0])

    return q


def quadratic(critic: LinearCritic) -> QuadraticCritic:
    """A concave quadratic critic in a box (evaluated by esa-core), from a linear one's numbers."""
    box = np.array([0.5, 1.0])
    return QuadraticCritic(critic.gain, -np.abs(critic.gain[:, ::-1]), critic.offset, -box, box)


CRITICS = {"linear": lambda critic: critic, "curved": curved, "quadratic": quadratic}


def comparable(states):
    return [
        (s.step, s.episodes_completed, s.probe_pending, s.shift.tolist(), s.response_mean_square)
        for s in states
    ]


@pytest.mark.parametrize("kind", sorted(CRITICS))
@pytest.mark.parametrize("paired", [False, True])
def test_the_actions_and_states_are_the_in_process_steps_bits(native, paired, kind):
    local = EsaClient.in_process()
    ahead = native.create_batch(CONFIG, N, use_stream=True)
    whole = local.create_batch(CONFIG, N)
    assert isinstance(ahead._stepper, AheadStepper)
    assert not isinstance(whole._stepper, AheadStepper)
    for actions, scales, linear, starts in script(300):
        critic = CRITICS[kind](linear)
        _, applied = ahead.step(actions, critic, starts, action_scales=scales, paired=paired)
        _, expected = whole.step(actions, critic, starts, action_scales=scales, paired=paired)
        np.testing.assert_array_equal(applied, expected)
    # states() reads the last answer first.
    assert comparable(ahead.states()) == comparable(whole.states())
    np.testing.assert_array_equal(ahead.steps, whole.steps)
    ahead.close()
    local.close()


def test_without_a_pipelining_stream_it_is_step(native):
    local = EsaClient.in_process()
    for batch in (
        native.create_batch(CONFIG, N, use_stream=False),
        local.create_batch(CONFIG, N),
    ):
        twin = local.create_batch(CONFIG, N)
        assert not isinstance(batch._stepper, AheadStepper)
        for actions, scales, critic, starts in script(40, seed=1):
            _, applied = batch.step(actions, critic, starts, action_scales=scales)
            _, expected = twin.step(actions, critic, starts, action_scales=scales)
            np.testing.assert_array_equal(applied, expected)
        batch.close()
    local.close()


def test_a_refused_step_raises_at_the_next_call_and_changes_nothing(native):
    batch = native.create_batch(CONFIG, N, use_stream=True)
    steps = script(10, seed=2)
    for actions, scales, critic, starts in steps:
        batch.step(actions, critic, starts, action_scales=scales)
    before = comparable(batch.states())
    tracked = batch.steps
    actions, scales, critic, _ = next(script(1, seed=3))
    gain = critic.gain.copy()
    gain[1, 0] = np.nan
    # Sent without waiting: this call returns actions, the server refuses the step.
    batch.step(actions, LinearCritic(gain, critic.offset), action_scales=scales)
    with pytest.raises(InvalidArgument, match="critic_gains: expected finite values"):
        batch.step(actions, critic, action_scales=scales)
    assert comparable(batch.states()) == before
    np.testing.assert_array_equal(batch.steps, tracked)
    # The refused step is due again, and goes through.
    batch.step(actions, critic, action_scales=scales)
    batch.flush()
    np.testing.assert_array_equal(batch.steps, tracked + 1)
    assert [s.step for s in batch.states()] == (tracked + 1).tolist()
    batch.close()


def test_a_refused_step_with_values_raises_at_the_next_call(native):
    batch = native.create_batch(CONFIG, 1, use_stream=True)
    q = curved(LinearCritic(np.ones((1, 2)), np.zeros(1)))
    batch.step(np.zeros((1, 2)), q, np.ones(1, bool))
    batch.flush()
    # Another client moves the session on: the values went with a probe out of turn.
    other = native.get_session(batch.ids[0])
    other.probe(np.zeros(2))
    other.report(0.0)
    before = comparable(batch.states())
    batch.step(np.zeros((1, 2)), q)
    with pytest.raises(StepMismatch):
        batch.flush()
    assert comparable(batch.states()) == before
    batch.close()


@pytest.mark.parametrize("paired", [False, True])
def test_bad_critic_values_are_refused_at_once_and_nothing_is_sent(native, paired):
    batch = native.create_batch(CONFIG, N, use_stream=True)
    actions, scales, critic, starts = next(script(1, seed=8))
    batch.step(actions, curved(critic), starts, action_scales=scales, paired=paired)
    before, tracked = comparable(batch.states()), batch.steps
    rows = 2 * N if paired else N
    for values, match in [
        (lambda points: np.zeros(N + 1), rf"expected critic values of shape \({rows},\)"),
        (lambda points: np.zeros((rows, 1)), rf"expected critic values of shape \({rows},\)"),
        (lambda points: np.full(rows, np.nan), "expected finite critic values"),
        (lambda points: np.r_[np.zeros(rows - 1), np.inf], "expected finite critic values"),
    ]:
        with pytest.raises(ValueError, match=match):
            batch.step(actions, values, action_scales=scales, paired=paired)
        np.testing.assert_array_equal(batch.steps, tracked)
    assert comparable(batch.states()) == before
    # Nothing was sent: the next good step is the one due.
    batch.step(actions, curved(critic), action_scales=scales, paired=paired)
    batch.flush()
    np.testing.assert_array_equal(batch.steps, tracked + 1)
    batch.close()


def test_a_bad_quadratic_critic_is_refused_at_once_in_every_transports_words(native):
    batch = native.create_batch(CONFIG, N, use_stream=True)
    actions, scales, critic, starts = next(script(1, seed=5))
    good = quadratic(critic)
    batch.step(actions, good, starts, action_scales=scales)
    before, tracked = comparable(batch.states()), batch.steps
    for bad, match in [
        (good._replace(curvature=-good.curvature), "critic: expected curvature <= 0"),
        (good._replace(gain=good.gain[:2]), r"critic: expected gain of shape \(3, 2\)"),
        (good._replace(offset=np.full(N, np.nan)), "critic: expected a finite offset"),
        (good._replace(low=good.high, high=good.low), "critic: expected low <= high"),
    ]:
        with pytest.raises(ValueError, match=match):
            batch.step(actions, bad, action_scales=scales)
        np.testing.assert_array_equal(batch.steps, tracked)
    assert comparable(batch.states()) == before
    batch.step(actions, good, action_scales=scales)
    batch.flush()
    np.testing.assert_array_equal(batch.steps, tracked + 1)
    batch.close()


def test_bad_actions_are_refused_at_once_and_nothing_is_sent(native):
    batch = native.create_batch(CONFIG, N, use_stream=True)
    actions, scales, critic, starts = next(script(1, seed=4))
    batch.step(actions, critic, starts, action_scales=scales)
    before = comparable(batch.states())
    bad = actions.copy()
    bad[2, 1] = np.inf
    with pytest.raises(InvalidArgument, match=r"item 2: .*action\[1\]: expected a finite number"):
        batch.step(bad, critic, action_scales=scales)
    with pytest.raises(InvalidArgument, match="action_scale"):
        batch.step(actions, critic, action_scales=-scales)
    with pytest.raises(ValueError, match="critic: expected gain of shape"):
        batch.step(actions, LinearCritic(critic.gain[:2], critic.offset))
    assert comparable(batch.states()) == before
    batch.close()


def test_a_step_out_of_turn_is_a_step_mismatch_one_call_late(native):
    batch = native.create_batch(CONFIG, 1, use_stream=True)
    critic = LinearCritic(np.ones((1, 2)), np.zeros(1))
    batch.step(np.zeros((1, 2)), critic, np.ones(1, bool))
    batch.flush()
    # Another client moves the session on behind this batch's back.
    other = native.get_session(batch.ids[0])
    other.probe(np.zeros(2))
    other.report(0.0)
    batch.step(np.zeros((1, 2)), critic)
    with pytest.raises(StepMismatch):
        batch.flush()
    batch.close()


@pytest.mark.parametrize("kind", sorted(CRITICS))
def test_a_lost_answer_of_an_applied_step_changes_nothing(native, monkeypatch, kind):
    batch, twin = (native.create_batch(CONFIG, N, use_stream=True) for _ in "ab")
    for actions, scales, critic, starts in script(5, seed=5):
        for b in (batch, twin):
            b.step(actions, CRITICS[kind](critic), starts, action_scales=scales)
    ahead = batch._batch
    receive = ahead.receive_step
    calls = []

    def broken():
        calls.append(1)
        if len(calls) == 1:
            receive()  # the answer is read, then lost on the way
            raise ServerUnavailable("the connection dropped", StatusCode.UNAVAILABLE)
        return receive()

    monkeypatch.setattr(ahead, "receive_step", broken)
    sent, _, sent_critic, _ = next(script(1, seed=6))
    for b in (batch, twin):
        b.step(sent, CRITICS[kind](sent_critic))  # sends step 5
    actions, scales, critic, _ = next(script(1, seed=7))
    # The sessions' states say that step 5 was applied: its shifts are theirs, and the batch
    # goes on as the one whose answer arrived.
    applied = [
        b.step(actions, CRITICS[kind](critic), action_scales=scales)[1] for b in (batch, twin)
    ]
    np.testing.assert_array_equal(*applied)
    assert comparable(batch.states()) == comparable(twin.states())
    assert [s.step for s in batch.states()] == [7] * N
    assert batch.sessions_restored == 0
    for b in (batch, twin):
        b.close()


def test_step_ahead_refuses_bad_configs_and_arrays():
    good = CONFIG.to_proto().SerializeToString()
    other = SessionConfig(
        action_dim=3, dt=0.02, amplitude=[0.3], frequency=[40.0], learning_rate=[0.5]
    )
    with pytest.raises(ValueError, match="expected one or more configs of one action_dim"):
        StepAhead([])
    with pytest.raises(ValueError, match="expected one or more configs of one action_dim"):
        StepAhead([good, other.to_proto().SerializeToString()])
    with pytest.raises(EngineError, match="config: expected an encoded esa.v1.SessionConfig"):
        StepAhead([b"\xff\xff"])
    invalid = CONFIG.to_proto()
    invalid.dt = -1.0
    with pytest.raises(EngineError, match="dt"):
        StepAhead([invalid.SerializeToString()])
    applier = StepAhead([good] * 2)
    zeros = np.zeros((2, 2))
    for shifts, actions, scales, match in [
        (np.zeros((2, 3)), zeros, None, "shifts: expected 4 values, got 6"),
        (zeros, np.zeros(3), None, "actions: expected 4 values, got 3"),
        (zeros, zeros, np.ones(3), "action_scales: expected 0 or 4 values, got 3"),
        (np.array([[0.0, np.nan], [0.0, 0.0]]), zeros, None, r"item 0: .*shift\[1\]"),
        (zeros, zeros, np.array([[1.0, 1.0], [0.0, 1.0]]), r"item 1: .*action_scale\[0\]"),
    ]:
        with pytest.raises(EngineError, match=match) as refused:
            applier.probes(shifts, np.zeros(2, np.uint64), actions, scales)
        assert refused.value.code == StatusCode.INVALID_ARGUMENT
    with pytest.raises(EngineError, match="steps: expected 2 values, got 3"):
        applier.probes(zeros, np.zeros(3, np.uint64), zeros)
    with pytest.raises((ValueError, OverflowError), match="step"):
        applier.probes(zeros, np.array([0, -1]), zeros)


@pytest.mark.parametrize("paired", [False, True])
def test_the_quadratic_critics_values_come_with_the_probes(paired):
    applier = StepAhead([CONFIG.to_proto().SerializeToString()] * N)
    for t, (actions, scales, linear, _) in enumerate(script(20, seed=6)):
        critic, shifts, steps = quadratic(linear), 0.1 * actions[::-1], np.full(N, t)
        probes, applied, q, refs = applier.probes_quadratic(
            shifts, steps, actions, scales, critic, paired
        )
        np.testing.assert_array_equal(
            (probes, applied), applier.probes(shifts, steps, actions, scales)
        )
        np.testing.assert_array_equal(q, critic(probes))
        assert refs is None if not paired else np.array_equal(refs, critic(applied))
    with pytest.raises(EngineError, match="critic_curvatures: expected values <= 0") as refused:
        applier.probes_quadratic(
            shifts, steps, actions, scales, critic._replace(curvature=-critic.curvature), paired
        )
    assert refused.value.code == StatusCode.INVALID_ARGUMENT


def test_probes_ahead_are_the_servers_probes(native):
    ahead = native.create_batch(CONFIG, N, use_stream=True)
    waiting = native.create_batch(CONFIG, N)  # unary calls: the probes come from the server
    for actions, scales, critic, starts in script(60, seed=9):
        q = curved(critic)
        probes, applied = ahead.step(actions, q, starts, action_scales=scales)
        server_probes, server_applied = waiting.step(actions, q, starts, action_scales=scales)
        np.testing.assert_array_equal(probes, server_probes)
        np.testing.assert_array_equal(applied, server_applied)
    ahead.close()
    waiting.close()


def test_the_native_batch_needs_a_stream_and_a_step_sent(native):
    critic = LinearCritic(np.ones((N, 2)), np.zeros(N))
    unary = native.create_batch(CONFIG, N, use_stream=False)._batch._batch
    with pytest.raises(ValueError, match="expected a batch opened with use_stream=True"):
        unary.send_step_linear(
            np.zeros(N, np.uint64),
            np.zeros((N, 2)),
            np.ones(N, bool),
            None,
            critic.gain,
            critic.offset,
            False,
        )
    with pytest.raises(ValueError, match="expected a batch opened with use_stream=True"):
        unary.send_step(
            np.zeros(N, np.uint64), np.zeros((N, 2)), np.ones(N, bool), None, np.zeros(N), None
        )
    streamed = native.create_batch(CONFIG, N, use_stream=True)._batch._batch
    with pytest.raises(StatusError, match="no step was sent ahead on this batch"):
        streamed.receive_step()
