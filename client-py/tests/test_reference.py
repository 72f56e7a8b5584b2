"""The in-process reference against a literal scalar transcription of CONTRACT.md section 1."""

import math

import numpy as np
import pytest
from reference_law import ReferenceBatch, ReferenceSession

from esa_client import InvalidArgument, SessionConfig, SessionNotFound, StepMismatch


def literal_episode(config: SessionConfig, actions, qs):
    """One episode of the update law, written element by element from the contract."""
    d = config.action_dim
    k, w, alpha = (config.vector(n) for n in ("amplitude", "frequency", "learning_rate"))
    lo, hi = config.vector("action_low"), config.vector("action_high")
    cutoff = config.highpass_cutoff or min(config.frequency) / 10
    beta = 1 / (1 + cutoff * config.dt)
    limit = config.shift_limit or math.inf
    v = [0.0] * d
    x_prev = y_prev = None
    probes, improved = [], []
    for t, (a, q) in enumerate(zip(actions, qs, strict=True)):
        s = [math.sin(w[i] * (t * config.dt)) for i in range(d)]
        probes.append([min(max(a[i] + (v[i] + k[i] * s[i]), lo[i]), hi[i]) for i in range(d)])
        if config.disable_highpass:
            h = q
        else:
            if x_prev is None:
                x_prev, y_prev = q, 0.0
            h = beta * (y_prev + q - x_prev)
            x_prev, y_prev = q, h
        v = [min(max(v[i] + alpha[i] * s[i] * h, -limit), limit) for i in range(d)]
        improved.append([min(max(a[i] + v[i], lo[i]), hi[i]) for i in range(d)])
    return np.array(probes), np.array(improved)


@pytest.mark.parametrize("disable_highpass", [False, True])
def test_matches_literal_transcription(disable_highpass):
    rng = np.random.default_rng(0)
    config = SessionConfig(
        action_dim=3,
        dt=0.05,
        amplitude=[0.2, 0.1, 0.3],
        frequency=[20.0, 15.0, 10.0],
        learning_rate=0.4,
        disable_highpass=disable_highpass,
        action_low=-1.0,
        action_high=[1.0, 2.0, 0.5],
        shift_limit=0.7,
    )
    actions = rng.normal(size=(40, 3))
    qs = rng.normal(size=40) * 5
    want_probes, want_actions = literal_episode(config, actions, qs)
    session = ReferenceSession(config)
    for t in range(40):
        np.testing.assert_allclose(session.probe(actions[t]), want_probes[t], rtol=0, atol=1e-12)
        np.testing.assert_allclose(session.report(qs[t]), want_actions[t], rtol=0, atol=1e-12)
    assert session.step == 40


def test_first_report_of_each_episode_leaves_shift_at_zero():
    config = SessionConfig(action_dim=1, dt=0.1, amplitude=0.2, frequency=5.0, learning_rate=1.0)
    session = ReferenceSession(config)
    for episode in range(3):
        session.probe([0.0], episode_start=True)
        # s = sin(0) = 0 at t = 0 and the filter output is 0: no shift either way.
        np.testing.assert_array_equal(session.report(123.0 * (episode + 1)), [0.0])
        session.probe([0.0])
        session.report(-50.0)
        assert session.state().shift[0] != 0.0
    assert session.state().episodes_completed == 2


def test_lr_decay_and_max_episodes():
    config = SessionConfig(
        action_dim=1,
        dt=0.1,
        amplitude=0.5,
        frequency=5.0,
        learning_rate=1.0,
        disable_highpass=True,
        lr_decay=0.5,
        max_episodes=2,
    )
    session = ReferenceSession(config)
    shifts = []
    for _ in range(3):
        session.probe([0.0], episode_start=True)
        session.report(1.0)
        session.probe([0.0])
        shifts.append(session.report(1.0)[0])
    s1 = math.sin(5.0 * 0.1)
    assert shifts[0] == pytest.approx(s1)
    assert shifts[1] == pytest.approx(0.5 * s1)
    assert shifts[2] == 0.0  # pass-through from episode 2 on
    assert session.probe([3.0])[0] == 3.0


def test_retry_and_step_rules():
    config = SessionConfig(action_dim=2, dt=0.1, amplitude=0.2, frequency=5.0, learning_rate=1.0)
    session = ReferenceSession(config)
    with pytest.raises(StepMismatch):
        session.report(1.0)
    first = session.probe([0.1, 0.2])
    np.testing.assert_array_equal(session.probe([0.1, 0.2]), first)  # probe retry
    session.report(1.0)
    session.probe([0.3, 0.3])
    action = session.report(2.0)
    np.testing.assert_array_equal(session.report(2.0, step=1), action)  # report retry
    assert session.state().step == 2
    with pytest.raises(StepMismatch):
        session.report(2.0, step=0)
    with pytest.raises(StepMismatch):
        session.probe([0.0, 0.0], step=5)
    with pytest.raises(InvalidArgument):
        session.probe([np.nan, 0.0])
    with pytest.raises(InvalidArgument):
        session.probe([0.0])
    assert session.state().step == 2
    session.close()
    with pytest.raises(SessionNotFound):
        session.probe([0.0, 0.0])


def test_batch_is_all_or_nothing_and_nonfinite_update_is_skipped():
    config = SessionConfig(
        action_dim=1,
        dt=0.1,
        amplitude=1.0,
        frequency=5.0,
        learning_rate=1e300,
        disable_highpass=True,
    )
    batch = ReferenceBatch([config, config])
    batch.probe(np.zeros((2, 1)))
    batch.report([0.0, 0.0])
    batch.probe(np.zeros((2, 1)))
    with pytest.raises(InvalidArgument):
        batch.report([1.0, np.inf])
    assert batch.states()[0].probe_pending
    out = batch.report([1e300, 1.0])
    assert np.all(np.isfinite(out))
    assert batch.states()[0].shift[0] == 0.0  # alpha * s * q overflowed: skipped
    assert batch.states()[1].shift[0] != 0.0
