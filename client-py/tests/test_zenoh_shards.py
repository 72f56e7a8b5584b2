"""Sessions spread over N server processes by the documented hash, working as on one server."""

import hashlib
import os
import signal
import time
import uuid

import numpy as np
import pytest

from esa_client import (
    EsaClient,
    InvalidArgument,
    ServerUnavailable,
    SessionConfig,
    SessionNotFound,
    StatusCode,
)
from esa_client.sharding import shard_of

CONFIG = SessionConfig(
    action_dim=2, dt=0.05, amplitude=0.2, frequency=[10.0, 6.0], learning_rate=0.5
)


def spread_ids(tag, n):
    """N fresh ids owning sessions on both shards (ids are random: draw until they do)."""
    while True:
        ids = [f"{tag}-{k}-{uuid.uuid4()}" for k in range(n)]
        if {shard_of(i, 2) for i in ids} == {0, 1}:
            return ids


@pytest.fixture(scope="module")
def sharded(server_bin):
    with EsaClient.spawn(server_bin, transport="zenoh", shards=2) as client:
        yield client


@pytest.fixture(scope="module")
def shard_grpc(sharded):
    """A gRPC client per shard process, to see which process holds which session."""
    clients = [EsaClient.connect(s.address, token=s.token) for s in sharded.servers]
    yield clients
    for client in clients:
        client.close()


def test_the_hash_is_the_documented_one():
    # Pinned values: any client in any language must route these ids the same way.
    assert [shard_of(f"session-{i}", 2) for i in range(8)] == [1, 0, 1, 1, 1, 0, 1, 0]
    assert hashlib.sha256(b"session-0").hexdigest()[:16] == "27ac7a3cd2914d45"
    assert shard_of("session-0", 1000) == 0x27AC7A3CD2914D45 % 1000 == 629
    assert shard_of("é", 7) == int.from_bytes(hashlib.sha256("é".encode()).digest()[:8], "big") % 7
    with pytest.raises(ValueError, match="shards >= 1"):
        shard_of("x", 0)


def test_sessions_live_on_their_shard_only(sharded, shard_grpc):
    ids = spread_ids("spread", 16)
    for session_id in ids:
        sharded.create_session(CONFIG, session_id)
    owners = [shard_of(i, 2) for i in ids]
    for session_id, owner in zip(ids, owners, strict=True):
        assert shard_grpc[owner].session_state(session_id).config == CONFIG
        with pytest.raises(SessionNotFound):
            shard_grpc[1 - owner].session_state(session_id)
    generated = sharded.create_session(CONFIG)  # a client-made id, routed the same way
    assert shard_grpc[shard_of(generated.id, 2)].session_state(generated.id).step == 0


@pytest.mark.parametrize("use_stream", [False, True], ids=["batch", "stream"])
def test_a_batch_across_shards_matches_one_server(sharded, server_bin, use_stream):
    n = 9
    ids = spread_ids("parity", n)
    rng = np.random.default_rng(3)
    inputs = [(rng.normal(size=(n, 2)), rng.random(n) < 0.2, rng.normal(size=n)) for _ in range(15)]
    answers = []
    with EsaClient.spawn(server_bin) as single:
        for client in (single, sharded):
            batch = client.create_batch(CONFIG, n, ids=ids, use_stream=use_stream)
            out = []
            for t, (actions, starts, q) in enumerate(inputs):
                out.append(batch.probe(actions, starts | (t == 0)))
                out.append(batch.report(q))
            out += [s.shift for s in batch.states()]
            batch.close()
            answers.append(out)
    for a, b in zip(*answers, strict=True):
        np.testing.assert_array_equal(a, b)


def test_batch_errors_name_the_item_of_the_whole_batch(sharded):
    ids = [f"err-{i}-{uuid.uuid4()}" for i in range(6)]
    batch = sharded.create_batch(CONFIG, 6, ids=ids)
    actions = np.zeros((6, 2))
    actions[4, 0] = np.nan
    with pytest.raises(InvalidArgument, match=r"^item 4: .*\(shard \d\)") as info:
        batch.probe(actions, [True] * 6)
    assert info.value.index == 4
    batch.probe(np.zeros((6, 2)), [True] * 6)
    assert batch.report(np.arange(6.0)).shape == (6, 2)


def test_a_killed_shard_fails_fast_and_the_other_keeps_serving(server_bin):
    with EsaClient.spawn(server_bin, transport="zenoh", shards=2, timeout=5.0) as client:
        client.reconnect_timeout = 0  # batches raise the first failure, as unary calls do
        ids = spread_ids("kill", 8)
        batch = client.create_batch(CONFIG, 8, ids=ids)
        batch.probe(np.zeros((8, 2)), [True] * 8)
        batch.report(np.ones(8))
        survivor = client.get_session(next(i for i in ids if shard_of(i, 2) == 0))
        lost = client.get_session(next(i for i in ids if shard_of(i, 2) == 1))

        victim = client.servers[1]
        os.kill(victim.pid, signal.SIGKILL)
        victim.stop()  # reaps the process

        start = time.monotonic()
        with pytest.raises(ServerUnavailable, match="shard/1") as info:
            lost.probe([0.0, 0.0])
        assert time.monotonic() - start < 2.0, "a dead shard must not cost the full deadline"
        assert info.value.code == StatusCode.UNAVAILABLE
        with pytest.raises(ServerUnavailable, match=r"shard/1.*\(shard 1\)"):
            batch.probe(np.zeros((8, 2)))
        assert not client.healthy()
        for _ in range(3):  # the live shard is unaffected
            survivor.probe([0.1, 0.1])
            survivor.report(1.0)
        assert survivor.state().step == 4
