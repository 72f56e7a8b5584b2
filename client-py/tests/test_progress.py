"""A session's progress (episode count, the normalization's mean square) survives its loss.

``restore_sessions`` with ``progress`` recreates a lost session at an episode start with the
episode count and mean square given, on every transport alike (in-process, over gRPC); a bad
progress is refused as the server refuses it; batch answers carry what the client last saw.
"""

import math

import numpy as np
import pytest

from esa_client import EsaClient, InvalidArgument, SessionConfig
from esa_client.state import SessionProgress

CONFIG = SessionConfig(
    action_dim=2,
    dt=0.02,
    amplitude=0.2,
    frequency=[31.4, 15.7],
    learning_rate=0.05,
    lr_decay=0.7,
    normalize_response=True,
)


@pytest.fixture(params=["inprocess", "grpc"])
def client(request, server_bin):
    if request.param == "inprocess":
        with EsaClient.in_process() as c:
            yield c
    else:
        with EsaClient.spawn(server_bin) as c:
            yield c


def _episodes(batch, episodes: int, length: int = 6) -> None:
    rng = np.random.default_rng(1)
    for _ in range(episodes):
        for t in range(length):
            starts = np.full(batch.n, t == 0)
            probes, applied = batch.probe_applied(rng.normal(size=(batch.n, 2)), starts)
            q = -np.sum(np.concatenate([probes, applied]) ** 2, axis=1)
            batch.report(q[: batch.n], q_references=q[batch.n :], defer=True)
    batch.flush()


def test_a_closed_session_comes_back_with_its_progress(client):
    batch = client.create_batch(CONFIG, 2)
    _episodes(batch, 4)
    before = [state.progress for state in batch.states()]
    assert [p.episodes_completed for p in before] == [3, 3]
    assert all(p.response_mean_square is not None for p in before)
    for session_id in batch.ids:
        client.transport.close_session(session_id)
    assert client.restore_sessions(batch.ids, batch.configs, before) == 2
    after = batch.states()
    assert [state.progress for state in after] == before
    assert [(state.step, state.probe_pending) for state in after] == [(0, False)] * 2
    assert all(not state.shift.any() for state in after)
    # An existing session is newer than any progress: it stays as it is.
    assert client.restore_sessions(batch.ids, batch.configs, [SessionProgress(9)] * 2) == 0
    assert [state.progress for state in batch.states()] == before


def test_a_batch_restores_what_its_last_answer_said(client):
    batch = client.create_batch(CONFIG, 2)
    _episodes(batch, 3)
    seen = batch._batch.progress() if hasattr(batch._batch, "progress") else None
    for session_id in batch.ids:
        client.transport.close_session(session_id)
    batch.restore()
    states = batch.states()
    if seen is None:
        # In-process, nothing is lost but by closing: the batch has no answers to go by.
        assert [s.episodes_completed for s in states] == [0, 0]
    else:
        assert [s.progress for s in states] == seen
        assert [s.episodes_completed for s in states] == [2, 2]


def test_a_bad_progress_is_refused(client):
    plain = SessionConfig(action_dim=1, dt=0.02, amplitude=0.2, frequency=10.0, learning_rate=0.1)
    with pytest.raises(InvalidArgument, match="response_mean_square: expected none"):
        client.restore_sessions(["p"], plain, [SessionProgress(1, 2.0)])
    with pytest.raises(ValueError, match=r"expected one progress per session id \(2\), got 1"):
        client.restore_sessions(["a", "b"], CONFIG, [SessionProgress(1)])
    # Nothing was created.
    assert client.restore_sessions(["p"], plain) == 1


def test_progress_is_checked_and_read_from_batch_answers():
    with pytest.raises(ValueError, match="expected episodes_completed in"):
        SessionProgress(-1)
    with pytest.raises(ValueError, match="expected a finite response_mean_square >= 0"):
        SessionProgress(0, math.nan)
    with pytest.raises(ValueError, match="expected a finite response_mean_square >= 0"):
        SessionProgress(0, -0.5)
    assert SessionProgress.from_batch_answer([2, 5], [-1.0, 0.25]) == [
        SessionProgress(2, None),
        SessionProgress(5, 0.25),
    ]
    assert SessionProgress.from_batch_answer([1], []) == [SessionProgress(1, None)]
    with pytest.raises(ValueError, match="expected one mean square per session"):
        SessionProgress.from_batch_answer([1, 2], [0.5])
    wire = SessionProgress(3, 0.5).to_proto()
    assert (wire.episodes_completed, wire.response_mean_square) == (3, 0.5)
    assert not SessionProgress(3).to_proto().HasField("response_mean_square")
