"""Every server error reaches the caller as its typed exception, and changes nothing."""

import math
import uuid

import numpy as np
import pytest
import raw_grpc

from esa_client import (
    EsaClient,
    EsaError,
    InvalidArgument,
    ResourceExhausted,
    SessionAlreadyExists,
    SessionConfig,
    SessionNotFound,
    StatusCode,
    StepMismatch,
)
from esa_client._proto.esa.v1 import esa_pb2
from esa_client.errors import error_for, esa_error

CONFIG = SessionConfig(action_dim=2, dt=0.05, amplitude=0.2, frequency=10.0, learning_rate=0.5)


def unique(prefix):
    return f"{prefix}-{uuid.uuid4()}"


def raw_config(**change):
    message = CONFIG.to_proto()
    for name, value in change.items():
        if isinstance(value, list):
            getattr(message, name)[:] = value
        else:
            setattr(message, name, value)
    return message


def test_unknown_and_closed_sessions_are_not_found(client):
    with pytest.raises(SessionNotFound) as info:
        client.get_session(unique("missing"))
    assert info.value.code == StatusCode.NOT_FOUND and info.value.message
    session = client.create_session(CONFIG)
    session.close()
    for operation in (lambda: session.probe([0, 0]), session.end_episode, session.state):
        with pytest.raises(SessionNotFound):
            operation()
    with pytest.raises(SessionNotFound):
        session.close()


def test_garbage_values_are_invalid_and_change_nothing(client):
    session = client.create_session(CONFIG, unique("garbage"))
    session.probe([0.1, 0.2], episode_start=True)
    before = session.state()
    for bad in ([math.nan, 0.0], [0.0, math.inf], [0.0], [0.0, 0.0, 0.0], []):
        with pytest.raises(InvalidArgument):
            session.probe(bad)
    for bad in (math.nan, math.inf, -math.inf):
        with pytest.raises(InvalidArgument):
            session.report(bad)
    after = session.state()
    assert (after.step, after.probe_pending) == (before.step, before.probe_pending)
    assert np.array_equal(after.shift, before.shift)
    session.report(1.0)


def test_step_rules_give_step_mismatch(client):
    session = client.create_session(CONFIG, unique("steps"))
    with pytest.raises(StepMismatch):
        session.report(1.0)  # no pending probe
    with pytest.raises(StepMismatch, match="expected"):
        session.probe([0.0, 0.0], step=3)
    session.probe([0.0, 0.0])
    with pytest.raises(StepMismatch):
        session.report(1.0, step=1)
    session.report(1.0)
    with pytest.raises(StepMismatch):
        session.probe([0.0, 0.0], episode_start=True, step=1)
    assert session.state().step == 1


@pytest.mark.parametrize(
    "change",
    [
        dict(action_dim=0),
        dict(action_dim=5000),
        dict(dt=0.0),
        dict(dt=math.nan),
        dict(amplitude=[]),
        dict(amplitude=[-1.0]),
        dict(amplitude=[0.1, 0.2, 0.3]),
        dict(frequency=[]),
        dict(frequency=[math.pi / 0.05]),
        dict(learning_rate=[math.inf]),
        dict(highpass_cutoff=-1.0),
        dict(action_low=[1.0], action_high=[0.0]),
        dict(action_low=[math.nan]),
        dict(shift_limit=0.0),
        dict(lr_decay=1.5),
    ],
)
def test_bad_configs_are_invalid(client, change):
    with pytest.raises(InvalidArgument) as info:
        client.create_session(raw_config(**change))
    assert next(iter(change)) in info.value.message


def test_bad_session_ids(client):
    with pytest.raises(InvalidArgument):
        client.create_session(CONFIG, "x" * 129)
    session_id = unique("dup")
    first = client.create_session(CONFIG, session_id)
    assert client.create_session(CONFIG, session_id).id == first.id  # identical config: same
    other = SessionConfig(action_dim=2, dt=0.05, amplitude=0.3, frequency=10.0, learning_rate=0.5)
    with pytest.raises(SessionAlreadyExists):
        client.create_session(other, session_id)


@pytest.mark.parametrize("use_stream", [False, True], ids=["batch", "stream"])
def test_batch_garbage(client, use_stream):
    session_id = unique("twice")
    batch = client.create_batch(CONFIG, 2, ids=[session_id, session_id], use_stream=use_stream)
    with pytest.raises(InvalidArgument, match="item 1"):  # names the duplicate item
        batch.probe(np.zeros((2, 2)))
    assert not client.session_state(session_id).probe_pending
    good = client.create_batch(CONFIG, 3, use_stream=use_stream)
    good.probe(np.zeros((3, 2)), [True, True, True])
    good.report([1.0, 2.0, 3.0])
    with pytest.raises(StepMismatch):
        good.report([1.0, 2.0, 3.0], steps=[1, 1, 1])  # no pending probe
    with pytest.raises(InvalidArgument):
        good.probe(np.full((3, 2), np.nan))
    # After each error the stream stays usable.
    np.testing.assert_array_equal(good.steps, [1, 1, 1])
    assert good.probe(np.zeros((3, 2))).shape == (3, 2)
    with pytest.raises(ValueError, match="expected actions of shape"):
        good.probe(np.zeros((2, 2)))


@pytest.mark.parametrize("use_stream", [False, True], ids=["batch", "stream"])
def test_the_failing_item_travels_as_data(client, use_stream):
    batch = client.create_batch(CONFIG, 3, use_stream=use_stream)
    actions = np.zeros((3, 2))
    actions[2, 0] = np.nan
    with pytest.raises(InvalidArgument) as info:
        batch.probe(actions, [True, True, True])
    assert info.value.index == 2
    batch.probe(np.zeros((3, 2)), [True, True, True])
    with pytest.raises(StepMismatch) as info:
        batch.report([1.0, 2.0, 3.0], steps=[0, 5, 0])
    assert info.value.index == 1
    with pytest.raises(InvalidArgument) as info:  # the whole request, no item
        raw_grpc.call(raw_grpc.stub(client).ProbeBatch, esa_pb2.ProbeBatchRequest(), client.timeout)
    assert info.value.index is None
    with pytest.raises(SessionNotFound) as info:
        client.get_session(unique("missing"))
    assert info.value.index is None
    batch.close()


def test_raw_batch_requests_with_wrong_lengths(client):
    batch = client.create_batch(CONFIG, 2)
    requests = [
        esa_pb2.ProbeBatchRequest(session_ids=batch.ids, steps=[0], actions=[0.0] * 4),
        esa_pb2.ProbeBatchRequest(session_ids=batch.ids, steps=[0, 0], actions=[0.0] * 3),
        esa_pb2.ProbeBatchRequest(
            session_ids=batch.ids, steps=[0, 0], actions=[0.0] * 4, episode_starts=[True]
        ),
        esa_pb2.ProbeBatchRequest(),
    ]
    for request in requests:
        with pytest.raises(InvalidArgument):
            raw_grpc.call(raw_grpc.stub(client).ProbeBatch, request, client.timeout)
    report = esa_pb2.ReportBatchRequest(session_ids=batch.ids, steps=[0, 0], q_values=[1.0])
    with pytest.raises(InvalidArgument):
        raw_grpc.call(raw_grpc.stub(client).ReportBatch, report, client.timeout)


def test_session_limit_is_resource_exhausted(server_bin):
    with EsaClient.spawn(server_bin, max_sessions=2) as small:
        small.create_session(CONFIG)
        small.create_session(CONFIG)
        with pytest.raises(ResourceExhausted):
            small.create_session(CONFIG)
        with pytest.raises(ResourceExhausted):
            small.create_batch(CONFIG, 2)


def test_stream_error_codes_map_like_status_codes():
    error = esa_error(esa_pb2.StreamError(code=9, message="step 3 expected"))
    assert isinstance(error, StepMismatch) and error.code == StatusCode.FAILED_PRECONDITION
    assert "step 3 expected" in str(error)
    unknown = esa_error(esa_pb2.StreamError(code=13, message="boom"))
    assert type(unknown) is EsaError and unknown.code == StatusCode.INTERNAL


def test_stream_errors_carry_the_item():
    item = esa_pb2.BatchItem(index=2)
    error = esa_error(esa_pb2.StreamError(code=3, message="item 2: bad", item=item))
    assert isinstance(error, InvalidArgument) and error.index == 2
    assert esa_error(esa_pb2.StreamError(code=3, message="bad")).index is None


def test_the_clients_status_codes_are_grpcs_canonical_ones():
    """``StatusCode`` is the client's own enum, with gRPC's names and numbers."""
    import grpc

    assert {c.name: c.value for c in StatusCode} == {c.name: c.value[0] for c in grpc.StatusCode}
    assert StatusCode.of(99) is StatusCode.UNKNOWN
    assert str(error_for(5, "")) == "not_found [NOT_FOUND]"


def test_errors_speak_no_grpcio():
    """In-process and Zenoh errors carry the client's code, never grpcio's."""
    error = esa_error(esa_pb2.StreamError(code=14, message="gone"))
    assert type(error.code) is StatusCode and error.code == StatusCode.UNAVAILABLE == 14


def test_errors_pickle_with_their_code_and_item():
    """Ray and multiprocessing re-raise pickled copies: the code and the item survive."""
    import pickle

    for code in StatusCode:
        error = error_for(code.value, "what to fix", index=3)
        copy = pickle.loads(pickle.dumps(error))
        assert type(copy) is type(error)
        assert (copy.code, copy.message, copy.index, str(copy)) == (
            error.code,
            error.message,
            3,
            str(error),
        )
