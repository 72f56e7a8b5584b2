"""Over Zenoh every failure is the same typed exception as over gRPC, and never a hang."""

import math
import os
import signal
import time
import uuid

import numpy as np
import pytest
import zenoh

from esa_client import (
    DeadlineExceeded,
    EsaClient,
    InvalidArgument,
    ResourceExhausted,
    ServerUnavailable,
    SessionAlreadyExists,
    SessionConfig,
    SessionNotFound,
    StatusCode,
    StepMismatch,
    Unauthenticated,
)
from esa_client._proto.esa.v1 import esa_pb2
from esa_client.sidecar import ServerProcess
from esa_client.transports.zenoh import TwoServersAnswered, ZenohTransport, peer_config

CONFIG = SessionConfig(action_dim=2, dt=0.05, amplitude=0.2, frequency=10.0, learning_rate=0.5)


def unique(prefix):
    return f"{prefix}-{uuid.uuid4()}"


def test_not_found(zenoh_client):
    with pytest.raises(SessionNotFound) as info:
        zenoh_client.get_session(unique("missing"))
    assert info.value.code == StatusCode.NOT_FOUND and "not found" in info.value.message


def test_invalid_argument_changes_nothing(zenoh_client):
    session = zenoh_client.create_session(CONFIG, unique("bad"))
    session.probe([0.1, 0.2], episode_start=True)
    before = session.state()
    for bad in ([math.nan, 0.0], [0.0]):
        with pytest.raises(InvalidArgument) as info:
            session.probe(bad)
        assert info.value.code == StatusCode.INVALID_ARGUMENT
    bad_config = CONFIG.to_proto()
    bad_config.dt = 0.0
    with pytest.raises(InvalidArgument, match="dt"):
        zenoh_client.create_session(bad_config)
    after = session.state()
    assert (after.step, after.probe_pending) == (before.step, before.probe_pending)
    np.testing.assert_array_equal(after.shift, before.shift)


def test_step_mismatch(zenoh_client):
    session = zenoh_client.create_session(CONFIG, unique("steps"))
    with pytest.raises(StepMismatch) as info:
        session.report(1.0)
    assert info.value.code == StatusCode.FAILED_PRECONDITION
    with pytest.raises(StepMismatch, match="expected"):
        session.probe([0.0, 0.0], step=3)


def test_already_exists(zenoh_client):
    session_id = unique("dup")
    zenoh_client.create_session(CONFIG, session_id)
    other = SessionConfig(action_dim=2, dt=0.05, amplitude=0.3, frequency=10.0, learning_rate=0.5)
    with pytest.raises(SessionAlreadyExists) as info:
        zenoh_client.create_session(other, session_id)
    assert info.value.code == StatusCode.ALREADY_EXISTS


def test_resource_exhausted(server_bin):
    with EsaClient.spawn(server_bin, transport="zenoh", max_sessions=1) as small:
        small.create_session(CONFIG)
        with pytest.raises(ResourceExhausted) as info:
            small.create_session(CONFIG)
        assert info.value.code == StatusCode.RESOURCE_EXHAUSTED


@pytest.mark.parametrize("use_stream", [False, True], ids=["batch", "stream"])
def test_batch_errors_name_the_item_and_change_nothing(zenoh_client, use_stream):
    batch = zenoh_client.create_batch(CONFIG, 3, use_stream=use_stream)
    actions = np.zeros((3, 2))
    actions[2, 1] = math.inf
    with pytest.raises(InvalidArgument, match="item 2") as info:
        batch.probe(actions, [True, True, True])
    assert info.value.index == 2
    assert not any(s.probe_pending for s in batch.states())
    with pytest.raises(StepMismatch):
        batch.report([1.0, 2.0, 3.0])  # nothing was probed
    batch.probe(np.zeros((3, 2)), [True, True, True])
    assert batch.report([1.0, 2.0, 3.0]).shape == (3, 2)


def test_garbage_bytes_get_a_stream_error_payload(zenoh_client):
    """The wire format itself: a reply error whose payload is a StreamError message.

    The spawned server requires its token as the query's attachment; without it, even
    garbage gets UNAUTHENTICATED.
    """
    expected = {
        None: StatusCode.UNAUTHENTICATED,
        zenoh_client.server.token: StatusCode.INVALID_ARGUMENT,
    }
    with zenoh.open(peer_config(zenoh_client.address.split(","), 5.0)) as session:
        for token, code in expected.items():
            replies = list(
                session.get("esa/v1/Probe", payload=b"\xff\xff\xff", attachment=token, timeout=5.0)
            )
            assert len(replies) == 1 and replies[0].err is not None
            error = esa_pb2.StreamError.FromString(replies[0].err.payload.to_bytes())
            assert error.code == code and error.message


def test_without_the_token_calls_are_unauthenticated(zenoh_client):
    with EsaClient.connect(
        zenoh_client.address.split(","), transport="zenoh", timeout=5.0, check=False
    ) as stranger:
        assert isinstance(stranger.transport, ZenohTransport)
        with pytest.raises(Unauthenticated):
            stranger.create_session(CONFIG)


def test_a_second_server_on_the_same_keys_is_detected(server_bin, zenoh_client):
    """Two servers answering one key (here a second real one; on an open network it
    could be an impostor): the client trusts neither answer."""
    token = zenoh_client.server.token
    impostor = ServerProcess(server_bin, token=token, extra_args=["--zenoh"])
    try:
        locators = impostor.announced("zenoh listening on ", 30.0)
        endpoints = [*zenoh_client.address.split(","), *locators]
        # The check when connecting already sees both.
        with pytest.raises(TwoServersAnswered, match="answered 2 times"):
            EsaClient.connect(endpoints, transport="zenoh", timeout=5.0, token=token)
        with EsaClient.connect(
            endpoints, transport="zenoh", timeout=5.0, token=token, check=False
        ) as confused:
            with pytest.raises(TwoServersAnswered, match="answered 2 times"):
                confused.create_session(CONFIG)
    finally:
        impostor.stop()


def test_no_server_on_the_prefix_is_unavailable_at_once(zenoh_client):
    with EsaClient.connect(
        zenoh_client.address.split(","),
        transport="zenoh",
        prefix="nobody/here",
        timeout=5.0,
        check=False,
    ) as lost:
        assert not lost.healthy()
        start = time.monotonic()
        with pytest.raises(ServerUnavailable, match="nobody/here/GetSession") as info:
            lost.session_state("x")
        assert time.monotonic() - start < 1.0
        assert info.value.code == StatusCode.UNAVAILABLE


def test_unreachable_endpoint_is_unavailable():
    start = time.monotonic()
    with pytest.raises(ServerUnavailable, match="tcp/127.0.0.1:1"):
        EsaClient.connect("tcp/127.0.0.1:1", transport="zenoh", timeout=1.0)
    assert time.monotonic() - start < 5.0


def test_a_stopped_server_gives_deadline_exceeded(server_bin):
    with EsaClient.spawn(server_bin, transport="zenoh", timeout=0.5) as client:
        session = client.create_session(CONFIG)
        os.kill(client.server.pid, signal.SIGSTOP)
        # kill() returns before the child has stopped; waiting for the stop proves it.
        _, status = os.waitpid(client.server.pid, os.WUNTRACED)
        assert os.WIFSTOPPED(status)
        try:
            start = time.monotonic()
            with pytest.raises(DeadlineExceeded) as info:
                session.probe([0.0, 0.0], episode_start=True)
            assert 0.4 < time.monotonic() - start < 3.0
            assert info.value.code == StatusCode.DEADLINE_EXCEEDED
        finally:
            os.kill(client.server.pid, signal.SIGCONT)
        # The retry after the deadline is safe and answered.
        assert session.probe([0.0, 0.0], episode_start=True).shape == (2,)


@pytest.mark.parametrize(
    ("address", "arguments", "match"),
    [
        ("127.0.0.1:7447", {}, "endpoint"),
        ([], {}, "at least one Zenoh endpoint"),
        ("tcp/127.0.0.1:7447", {"prefix": "esa/*"}, "prefix"),
        ("tcp/127.0.0.1:7447", {"timeout": 0}, "timeout"),
        ("tcp/127.0.0.1:7447", {"shards": 0}, "shards >= 1"),
        ("tcp/127.0.0.1:7447", {"tls": object()}, "tls=None"),
    ],
)
def test_bad_arguments_are_value_errors(address, arguments, match):
    with pytest.raises(ValueError, match=match):
        EsaClient.connect(address, transport="zenoh", **arguments)


def test_bad_spawn_arguments_start_no_server(server_bin):
    with pytest.raises(ValueError, match="shards >= 1"):
        EsaClient.spawn(server_bin, transport="zenoh", shards=0)
    with pytest.raises(ValueError, match="without wildcards"):
        EsaClient.spawn(server_bin, transport="zenoh", prefix="esa/**")
    with pytest.raises(ValueError, match="shards with transport='zenoh' only"):
        EsaClient.spawn(server_bin, shards=2)
