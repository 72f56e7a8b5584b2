"""gRPC and Zenoh are two wires for one contract: identical calls give identical answers.

Both clients talk to the same server process (gRPC on a Unix socket, Zenoh on
loopback), so sessions created over one transport are usable over the other.
"""

import uuid

import numpy as np
import pytest

from esa_client import EsaClient, SessionConfig, SessionNotFound
from esa_client.transports.zenoh import peer_config

CONFIG = SessionConfig(
    action_dim=2,
    dt=0.05,
    amplitude=[0.2, 0.1],
    frequency=[10.0, 7.0],
    learning_rate=0.5,
    action_low=-1.0,
    action_high=1.0,
    lr_decay=0.9,
)


def session_script(client, session_id, config, seed):
    """Runs a fixed probe/report/end-episode sequence; returns every answer."""
    rng = np.random.default_rng(seed)
    session = client.create_session(config, session_id)
    out = []
    for episode in range(3):
        for t in range(12):
            probe = session.probe(rng.normal(size=config.action_dim), episode_start=t == 0)
            out.append(probe)
            out.append(session.report(float(-np.sum(probe**2) + rng.normal())))
        if episode == 1:
            out.append(np.array([session.end_episode()]))
    state = session.state()
    out += [state.shift, np.array([state.step, state.episodes_completed])]
    session.close()
    return out


def batch_script(client, ids, config, seed, use_stream):
    rng = np.random.default_rng(seed)
    batch = client.create_batch(config, len(ids), ids=ids, use_stream=use_stream)
    out = []
    for t in range(30):
        starts = rng.random(len(ids)) < (1.0 if t == 0 else 0.1)
        probes = batch.probe(rng.normal(size=(len(ids), config.action_dim)), starts)
        out += [probes, batch.report(-np.sum(probes**2, axis=1) + rng.normal(size=len(ids)))]
    out.append(batch.end_episode([0, 2]))
    out += [s.shift for s in batch.states()]
    batch.close()
    return out


def assert_identical(left, right):
    assert len(left) == len(right)
    for a, b in zip(left, right, strict=True):
        np.testing.assert_array_equal(a, b)


def test_unary_calls_answer_identically(zenoh_client, zenoh_grpc_client, make_config):
    for seed in range(3):
        config = make_config(np.random.default_rng(seed))
        over_grpc = session_script(zenoh_grpc_client, f"g-{uuid.uuid4()}", config, seed)
        over_zenoh = session_script(zenoh_client, f"z-{uuid.uuid4()}", config, seed)
        assert_identical(over_grpc, over_zenoh)


@pytest.mark.parametrize("use_stream", [False, True], ids=["batch", "stream"])
def test_batches_answer_identically(zenoh_client, zenoh_grpc_client, use_stream):
    n = 5
    grpc_ids = [f"g-{uuid.uuid4()}" for _ in range(n)]
    zenoh_ids = [f"z-{uuid.uuid4()}" for _ in range(n)]
    over_grpc = batch_script(zenoh_grpc_client, grpc_ids, CONFIG, 7, use_stream)
    over_zenoh = batch_script(zenoh_client, zenoh_ids, CONFIG, 7, use_stream)
    assert_identical(over_grpc, over_zenoh)


def test_a_session_moves_between_transports(zenoh_client, zenoh_grpc_client):
    created = zenoh_grpc_client.create_session(CONFIG)  # server-generated id over gRPC
    over_zenoh = zenoh_client.get_session(created.id)
    probe = over_zenoh.probe([0.1, -0.2], episode_start=True)
    assert zenoh_grpc_client.session_state(created.id).probe_pending
    improved = created.report(1.0)  # the gRPC handle carries on with the step Zenoh began
    assert created.step == 1 and improved.shape == (2,) and probe.shape == (2,)
    grpc_view, zenoh_view = created.state(), over_zenoh.state()
    assert grpc_view.config == zenoh_view.config == CONFIG
    assert (grpc_view.step, grpc_view.probe_pending) == (zenoh_view.step, zenoh_view.probe_pending)
    np.testing.assert_array_equal(grpc_view.shift, zenoh_view.shift)
    over_zenoh.close()
    with pytest.raises(SessionNotFound):  # closed over Zenoh means closed over gRPC
        created.state()


def test_health_and_readiness(zenoh_client):
    assert zenoh_client.healthy()
    zenoh_client.check(1.0)
    assert "esa/v1" in repr(zenoh_client)


@pytest.mark.parametrize("own_config", [False, True], ids=["endpoints", "zenoh-config"])
def test_a_second_client_connects_to_the_announced_locator(zenoh_client, own_config):
    endpoints = zenoh_client.address.split(",")
    config = peer_config(endpoints, 2.0) if own_config else None
    token = zenoh_client.server.token
    with EsaClient.connect(
        endpoints, transport="zenoh", timeout=2.0, zenoh_config=config, token=token
    ) as other:
        session = other.create_session(CONFIG)
        assert zenoh_client.session_state(session.id).step == 0
        session.close()
