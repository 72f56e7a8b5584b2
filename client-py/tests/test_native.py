"""esa_client._native (esa-core in-process) agrees with the real esa-server bit for bit.

Every script runs the same requests against the server (raw gRPC batches through the session-scoped
``client`` fixture) and against a native ``Engine``: probes with episode starts and action scales,
reports with and without references, retries, episode ends and GetSession snapshots. Every bad
input must raise the same gRPC status code (and name the same batch item) on both sides and change
nothing on either.
"""

import re
import threading
import uuid

import grpc
import numpy as np
import pytest
import raw_grpc

from esa_client import EsaClient, SessionConfig
from esa_client._native import (
    ALREADY_EXISTS,
    FAILED_PRECONDITION,
    INVALID_ARGUMENT,
    MAX_BATCH_ITEMS,
    NOT_FOUND,
    RESOURCE_EXHAUSTED,
    BatchHandle,
    Engine,
    EngineError,
)
from esa_client._proto.esa.v1 import esa_pb2


def config_bytes(config: SessionConfig | esa_pb2.SessionConfig) -> bytes:
    message = config.to_proto() if isinstance(config, SessionConfig) else config
    return message.SerializeToString()


def bits(values) -> np.ndarray:
    """The float64 values as their bit patterns, so that equality is bit for bit (-0.0 != 0.0)."""
    return np.ascontiguousarray(values, dtype=np.float64).ravel().view(np.uint64)


def assert_bits_equal(got, want):
    np.testing.assert_array_equal(bits(got), bits(want))


class Outcome:
    """What one call did on one side: a value, or an error's code, message and item index."""

    def __init__(self, value=None, code=None, message=None, index=None):
        self.value, self.code, self.message, self.index = value, code, message, index

    def __repr__(self):
        return f"Outcome(code={self.code}, index={self.index}, message={self.message!r})"


def server_outcome(call) -> Outcome:
    try:
        return Outcome(value=call())
    except grpc.RpcError as err:
        message = err.details()
        match = re.match(r"item (\d+): ", message)
        return Outcome(
            code=err.code().value[0],
            message=message,
            index=int(match.group(1)) if match else None,
        )


def native_outcome(call) -> Outcome:
    try:
        return Outcome(value=call())
    except EngineError as err:
        assert str(err) == err.message
        return Outcome(code=err.code, message=err.message, index=err.index)


class Pair:
    """The same sessions on the server and in a native engine, driven with the same requests."""

    def __init__(self, client: EsaClient, engine: Engine, configs, prefix: str):
        self.client, self.engine = client, engine
        self.ids = [f"native-{prefix}-{i}-{uuid.uuid4()}" for i in range(len(configs))]
        self.dims = [c.action_dim for c in configs]
        for session_id, config in zip(self.ids, configs, strict=True):
            message = config.to_proto()
            request = esa_pb2.CreateSessionRequest(session_id=session_id, config=message)
            assert (
                raw_grpc.stub(self.client).CreateSession(request, timeout=5).session_id
                == session_id
            )
            assert engine.create_session(session_id, config_bytes(message)) == session_id
        self.handle = engine.resolve(self.ids)
        self.steps = np.zeros(len(configs), dtype=np.uint64)

    # --- both sides -------------------------------------------------------------------------

    def probe(self, steps, actions, starts=None, scales=None, *, ids=None, handle=None):
        ids = self.ids if ids is None else ids
        request = esa_pb2.ProbeBatchRequest(
            session_ids=ids,
            steps=[int(s) for s in steps],
            actions=np.ravel(actions).tolist(),
            episode_starts=[] if starts is None else [bool(s) for s in starts],
            action_scales=[] if scales is None else np.ravel(scales).tolist(),
        )
        server = server_outcome(
            lambda: raw_grpc.stub(self.client).ProbeBatch(request, timeout=10),
        )
        native = native_outcome(
            lambda: self.engine.probe(
                self.handle if handle is None else handle,
                np.asarray(steps, dtype=np.uint64),
                actions,
                None if starts is None else np.asarray(starts, dtype=bool),
                scales,
            )
        )
        return self.agree(server, native, lambda s: (s.probes, s.actions))

    def report(self, steps, q, references=None, *, handle=None):
        request = esa_pb2.ReportBatchRequest(
            session_ids=self.ids,
            steps=[int(s) for s in steps],
            q_values=np.ravel(q).tolist(),
            q_references=[] if references is None else np.ravel(references).tolist(),
        )
        server = server_outcome(lambda: raw_grpc.stub(self.client).ReportBatch(request, timeout=10))
        native = native_outcome(
            lambda: self.engine.report(
                self.handle if handle is None else handle,
                np.asarray(steps, dtype=np.uint64),
                q,
                references,
            )
        )
        return self.agree(server, native, lambda s: (s.actions,))

    def end_episode(self, i: int) -> int:
        request = esa_pb2.EndEpisodeRequest(session_id=self.ids[i])
        server = raw_grpc.stub(self.client).EndEpisode(request, timeout=5).episodes_completed
        native = self.engine.end_episode(self.ids[i])
        assert server == native
        return native

    def states(self) -> list[bytes]:
        """GetSession of every session, asserting both sides agree bit for bit."""
        snapshots = []
        for session_id in self.ids:
            request = esa_pb2.GetSessionRequest(session_id=session_id)
            server = raw_grpc.stub(self.client).GetSession(request, timeout=5)
            native = esa_pb2.GetSessionResponse.FromString(self.engine.get_session(session_id))
            server_bytes = server.SerializeToString(deterministic=True)
            assert native.SerializeToString(deterministic=True) == server_bytes, (
                f"{session_id}: native {native} != server {server}"
            )
            snapshots.append(server_bytes)
        return snapshots

    def agree(self, server: Outcome, native: Outcome, fields):
        """Both succeeded with the same values (returned), or failed alike (the Outcome)."""
        if server.code is not None or native.code is not None:
            assert (native.code, native.index) == (server.code, server.index), (server, native)
            if server.code in (INVALID_ARGUMENT, FAILED_PRECONDITION):
                assert native.message == server.message
            return server
        want = [np.asarray(f, dtype=np.float64) for f in fields(server.value)]
        got = native.value if isinstance(native.value, tuple) else (native.value,)
        assert len(got) == len(want)
        for g, w in zip(got, want, strict=True):
            assert_bits_equal(g, w)
            if len(set(self.dims)) == 1:
                assert g.shape == (len(self.ids), self.dims[0])
        return got if len(got) > 1 else got[0]

    def refused(self, outcome, code, index=None):
        """`outcome` is an error with `code` and `index` on both sides (agree checked the rest)."""
        assert isinstance(outcome, Outcome), f"expected {code}, both sides succeeded"
        assert (outcome.code, outcome.index) == (code, index), outcome

    def close(self):
        for session_id in self.ids:
            raw_grpc.stub(self.client).CloseSession(
                esa_pb2.CloseSessionRequest(session_id=session_id), timeout=5
            )
            self.engine.close_session(session_id)


def q_of(rng, probes_flat, dims):
    """A smooth bounded objective per item plus noise."""
    values, offset = [], 0
    for d in dims:
        p = probes_flat[offset : offset + d]
        values.append(-5 * np.tanh(np.sum((p - 0.2) ** 2)) + rng.normal())
        offset += d
    return np.array(values)


@pytest.mark.parametrize("seed", range(8))
def test_random_scripts_match_the_server_bit_for_bit(client, make_config, seed):
    rng = np.random.default_rng(5000 + seed)
    n = int(rng.integers(1, 9))
    mixed = seed % 4 == 3  # sessions of different action_dim in one batch
    d = int(rng.integers(1, 5))
    configs = [make_config(rng, None if mixed else d) for _ in range(n)]
    pair = Pair(client, Engine(), configs, f"script{seed}")
    dims, total = pair.dims, sum(pair.dims)
    steps = np.zeros(n, dtype=np.uint64)
    for t in range(120):
        starts = rng.random(n) < (1.0 if t == 0 else 0.04)
        steps[starts] = 0
        actions = rng.normal(size=total) if mixed else rng.normal(size=(n, d))
        scales = rng.uniform(0.05, 2.0, size=np.shape(actions)) if rng.random() < 0.6 else None
        send_starts = starts if (starts.any() or rng.random() < 0.5) else None
        probes, applied = pair.probe(steps, actions, send_starts, scales)
        if rng.random() < 0.15:  # a probe retry of the same step replaces the pending action
            actions = rng.normal(size=np.shape(actions))
            probes, applied = pair.probe(steps, actions, None, scales)
        q = q_of(rng, np.ravel(probes), dims)
        references = q_of(rng, np.ravel(applied), dims) if rng.random() < 0.5 else None
        improved = pair.report(steps, q, references)
        if rng.random() < 0.15:  # a report retry of the step just applied returns it again
            again = pair.report(steps, q + 1.0, references)
            assert_bits_equal(again, improved)
        steps += 1
        if rng.random() < 0.05:
            i = int(rng.integers(n))
            pair.end_episode(i)
            steps[i] = 0
        if t % 20 == 0:
            pair.states()
    pair.states()
    pair.close()


def test_a_large_batch_releases_the_gil_and_matches(client, make_config):
    """N * D above DETACH_VALUES takes the GIL-released path; same bits as the server."""
    rng = np.random.default_rng(11)
    n, d = 40, 160
    configs = [make_config(rng, d) for _ in range(n)]
    pair = Pair(client, Engine(), configs, "large")
    steps = np.zeros(n, dtype=np.uint64)
    for t in range(4):
        actions = rng.normal(size=(n, d))
        probes, applied = pair.probe(steps, actions, [t == 0] * n, rng.uniform(0.1, 1, (n, d)))
        q = q_of(rng, np.ravel(probes), pair.dims)
        pair.report(steps, q, q_of(rng, np.ravel(applied), pair.dims))
        steps += 1
    pair.states()
    pair.close()


def started_pair(client, make_config, prefix, dims=(2, 1, 2)):
    """Three sessions after one probe + report and a pending probe at step 1."""
    rng = np.random.default_rng(3)
    configs = [make_config(rng, d) for d in dims]
    pair = Pair(client, Engine(), configs, prefix)
    total = sum(dims)
    pair.probe([0, 0, 0], rng.normal(size=total), [True] * 3)
    pair.report([0, 0, 0], [1.0, 2.0, 3.0])
    pair.probe([1, 1, 1], rng.normal(size=total))
    return pair


def test_bad_batches_raise_the_servers_codes_and_change_nothing(client, make_config):
    pair = started_pair(client, make_config, "bad")
    before = pair.states()
    total = 5
    good = np.linspace(-0.5, 0.5, total)
    nan_item2 = good.copy()
    nan_item2[4] = np.nan
    inf_item0 = good.copy()
    inf_item0[0] = -np.inf
    bad_scales = np.ones(total)
    bad_scales[2] = 0.0
    nan_scales = np.ones(total)
    nan_scales[3] = np.nan
    ones = np.ones(3)
    cases = [
        # probe: lengths (the whole request), then items
        (lambda: pair.probe([1, 1], good), INVALID_ARGUMENT, None),
        (lambda: pair.probe([1, 1, 1], good, [False, True]), INVALID_ARGUMENT, None),
        (lambda: pair.probe([1, 1, 1], good[:4]), INVALID_ARGUMENT, None),
        (lambda: pair.probe([1, 1, 1], np.append(good, 1.0)), INVALID_ARGUMENT, None),
        (lambda: pair.probe([1, 1, 1], good, None, np.ones(3)), INVALID_ARGUMENT, None),
        (lambda: pair.probe([1, 1, 1], nan_item2), INVALID_ARGUMENT, 2),
        (lambda: pair.probe([1, 1, 1], inf_item0), INVALID_ARGUMENT, 0),
        (lambda: pair.probe([1, 1, 1], good, None, bad_scales), INVALID_ARGUMENT, 1),
        (lambda: pair.probe([1, 1, 1], good, None, -np.ones(total)), INVALID_ARGUMENT, 0),
        (lambda: pair.probe([1, 1, 1], good, None, nan_scales), INVALID_ARGUMENT, 2),
        (lambda: pair.probe([1, 2, 1], good), FAILED_PRECONDITION, 1),
        (lambda: pair.probe([1, 1, 0], good), FAILED_PRECONDITION, 2),
        (lambda: pair.probe([1, 1, 1], good, [False, False, True]), FAILED_PRECONDITION, 2),
        # report: lengths, then items
        (lambda: pair.report([1, 1], ones), INVALID_ARGUMENT, None),
        (lambda: pair.report([1, 1, 1], ones[:2]), INVALID_ARGUMENT, None),
        (lambda: pair.report([1, 1, 1], ones, ones[:2]), INVALID_ARGUMENT, None),
        (lambda: pair.report([1, 1, 1], [1.0, np.nan, 1.0]), INVALID_ARGUMENT, 1),
        (lambda: pair.report([1, 1, 1], [1.0, 1.0, np.inf]), INVALID_ARGUMENT, 2),
        (lambda: pair.report([1, 1, 1], ones, [0.0, 0.0, -np.inf]), INVALID_ARGUMENT, 2),
        (lambda: pair.report([1, 3, 1], ones), FAILED_PRECONDITION, 1),
        (lambda: pair.report([2, 1, 1], ones), FAILED_PRECONDITION, 0),
    ]
    for call, code, index in cases:
        pair.refused(call(), code, index)
        assert pair.states() == before
    # The step just before is a replay only right after a report; here it is a step mismatch.
    pair.refused(pair.report([0, 0, 0], ones), FAILED_PRECONDITION, 0)
    pair.report([1, 1, 1], ones)
    # No probe pending at step 2: FAILED_PRECONDITION (report without probe).
    before = pair.states()
    pair.refused(pair.report([2, 2, 2], ones), FAILED_PRECONDITION, 0)
    assert pair.states() == before
    pair.close()


def test_unknown_repeated_and_malformed_ids(client, make_config):
    pair = started_pair(client, make_config, "ids")
    before = pair.states()
    engine = pair.engine
    good = np.zeros(5)
    ghost = f"native-ghost-{uuid.uuid4()}"
    long_id = "x" * 129
    # The server is sent the ids, the engine resolves them: same code and item.
    for ids, code, index in [
        ([pair.ids[0], ghost, pair.ids[2]], NOT_FOUND, 1),
        ([pair.ids[0], pair.ids[1], pair.ids[0]], INVALID_ARGUMENT, 2),
        ([pair.ids[0], long_id, pair.ids[2]], INVALID_ARGUMENT, 1),
        ([pair.ids[0], "", pair.ids[2]], INVALID_ARGUMENT, 1),
        ([], INVALID_ARGUMENT, None),
    ]:
        request = esa_pb2.ProbeBatchRequest(
            session_ids=ids, steps=[1] * len(ids), actions=good[: 2 * len(ids) - 1].tolist()
        )
        server = server_outcome(lambda r=request: raw_grpc.stub(client).ProbeBatch(r, timeout=5))
        native = native_outcome(lambda ids=ids: engine.resolve(ids))
        assert (server.code, server.index) == (code, index), server
        assert (native.code, native.index) == (code, index), native
        if code == INVALID_ARGUMENT:
            assert native.message == server.message
    too_many = [f"x{i}" for i in range(MAX_BATCH_ITEMS + 1)]
    request = esa_pb2.ProbeBatchRequest(session_ids=too_many, steps=[0] * len(too_many))
    server = server_outcome(lambda: raw_grpc.stub(client).ProbeBatch(request, timeout=30))
    native = native_outcome(lambda: engine.resolve(too_many))
    # (The server's wire decoder refuses it before the handler, in its own words.)
    assert (server.code, server.index) == (native.code, native.index) == (INVALID_ARGUMENT, None)
    assert pair.states() == before

    # A session closed after its handle was resolved is NOT_FOUND for its item, on both sides;
    # the others are untouched.
    stale = engine.resolve(pair.ids)
    raw_grpc.stub(client).CloseSession(
        esa_pb2.CloseSessionRequest(session_id=pair.ids[1]), timeout=5
    )
    engine.close_session(pair.ids[1])
    pair.refused(pair.probe([1, 1, 1], good, handle=stale), NOT_FOUND, 1)
    pair.refused(pair.report([1, 1, 1], np.ones(3), handle=stale), NOT_FOUND, 1)
    # Created again under the same id, the handle finds the new session (as the server does).
    config = make_config(np.random.default_rng(8), 1)
    raw_grpc.stub(client).CreateSession(
        esa_pb2.CreateSessionRequest(session_id=pair.ids[1], config=config.to_proto()), timeout=5
    )
    engine.create_session(pair.ids[1], config_bytes(config))
    pair.refused(pair.probe([0, 0, 1], good, handle=stale), FAILED_PRECONDITION, 0)
    pair.probe([1, 0, 1], good, [False, True, False], handle=stale)
    pair.states()
    pair.close()


def test_unary_calls_and_create_session_match_the_server(client, make_config):
    rng = np.random.default_rng(21)
    engine = Engine()
    config = make_config(rng, 3).to_proto()
    other = make_config(rng, 3).to_proto()
    session_id = f"native-create-{uuid.uuid4()}"

    def both(server_call, native_call):
        server = server_outcome(server_call)
        native = native_outcome(native_call)
        assert native.code == server.code, (server, native)
        if server.code == INVALID_ARGUMENT:
            assert native.message == server.message
        return server, native

    def create(sid, message):
        request = esa_pb2.CreateSessionRequest(session_id=sid, config=message)
        return both(
            lambda: raw_grpc.stub(client).CreateSession(request, timeout=5).session_id,
            lambda: engine.create_session(sid, config_bytes(message)),
        )

    server, native = create(session_id, config)
    assert server.value == native.value == session_id
    server, native = create(session_id, config)  # identical config: the same session
    assert server.value == native.value == session_id
    server, native = create(session_id, other)
    assert native.code == ALREADY_EXISTS
    bad = esa_pb2.SessionConfig()
    bad.CopyFrom(config)
    bad.frequency[:] = [1000.0]  # w * dt >= pi
    server, native = create(f"native-bad-{uuid.uuid4()}", bad)
    assert native.code == INVALID_ARGUMENT
    server, native = create("y" * 129, config)
    assert native.code == INVALID_ARGUMENT
    # An empty or absent id: the server and the engine generate a UUID.
    server, native = create("", config)
    assert uuid.UUID(native.value) and uuid.UUID(server.value)
    assert uuid.UUID(engine.create_session(None, config_bytes(config)))
    assert len(engine) == 3 and session_id in engine

    for sid, code in [(session_id, None), (f"native-none-{uuid.uuid4()}", NOT_FOUND), ("", 3)]:
        request = esa_pb2.GetSessionRequest(session_id=sid)
        server, native = both(
            lambda r=request: raw_grpc.stub(client).GetSession(r, timeout=5),
            lambda sid=sid: engine.get_session(sid),
        )
        assert native.code == code
        if code is None:
            got = esa_pb2.GetSessionResponse.FromString(native.value)
            assert got.SerializeToString(deterministic=True) == server.value.SerializeToString(
                deterministic=True
            )
        request = esa_pb2.EndEpisodeRequest(session_id=sid)
        server, native = both(
            lambda r=request: raw_grpc.stub(client).EndEpisode(r, timeout=5).episodes_completed,
            lambda sid=sid: engine.end_episode(sid),
        )
        assert server.value == native.value
    request = esa_pb2.CloseSessionRequest(session_id=session_id)
    for _ in range(2):  # closed, then NOT_FOUND
        server, native = both(
            lambda: raw_grpc.stub(client).CloseSession(request, timeout=5),
            lambda: engine.close_session(session_id),
        )
    assert native.code == NOT_FOUND
    assert session_id not in engine


def test_the_session_limit_is_resource_exhausted(server_bin, make_config):
    config = make_config(np.random.default_rng(4), 2).to_proto()
    engine = Engine(max_sessions=2)
    assert engine.max_sessions == 2
    with EsaClient.spawn(server_bin, max_sessions=2) as limited:
        for i in range(3):
            request = esa_pb2.CreateSessionRequest(session_id=f"s{i}", config=config)
            server = server_outcome(
                lambda r=request: raw_grpc.stub(limited).CreateSession(r, timeout=5)
            )
            native = native_outcome(
                lambda i=i: engine.create_session(f"s{i}", config_bytes(config))
            )
            assert server.code == native.code == (RESOURCE_EXHAUSTED if i == 2 else None)
        # At the limit, an existing id with its config is still answered.
        assert engine.create_session("s0", config_bytes(config)) == "s0"
        engine.close_session("s0")
        assert engine.create_session("s2", config_bytes(config)) == "s2"


def test_too_many_action_values_in_one_batch(client):
    """257 sessions of D = 4096 hold more than MAX_BATCH_VALUES (2^20) action values."""
    n, d = 257, 4096
    config = esa_pb2.SessionConfig(
        action_dim=d, dt=0.01, amplitude=[0.1], frequency=[10.0], learning_rate=[0.1]
    )
    engine = Engine()
    ids = [engine.create_session(f"big-{i}", config.SerializeToString()) for i in range(n)]
    actions = np.zeros((n, d))
    native = native_outcome(
        lambda: engine.probe(engine.resolve(ids), np.zeros(n, np.uint64), actions)
    )
    assert (native.code, native.index) == (INVALID_ARGUMENT, None)
    assert native.message.startswith("session_ids: the sessions' action_dim add up to 1052672")
    # The server's wire decoder refuses the same values before looking the sessions up.
    request = esa_pb2.ProbeBatchRequest(session_ids=ids, steps=[0] * n, actions=actions.ravel())
    server = server_outcome(lambda: raw_grpc.stub(client).ProbeBatch(request, timeout=60))
    assert (server.code, server.index) == (INVALID_ARGUMENT, None)


def test_array_arguments_are_converted_like_numpy(make_config):
    """Lists, float32, Fortran order and int64 steps give the results of C-order float64."""
    rng = np.random.default_rng(2)
    configs = [make_config(rng, 3) for _ in range(4)]

    def run(convert):
        engine = Engine()
        ids = [engine.create_session(f"s{i}", config_bytes(c)) for i, c in enumerate(configs)]
        handle = engine.resolve(ids)
        rng = np.random.default_rng(9)
        out = []
        for t in range(5):
            actions = rng.normal(size=(4, 3)).astype(np.float32).astype(np.float64)
            scales = rng.uniform(0.1, 1.0, size=(4, 3)).astype(np.float32).astype(np.float64)
            q = rng.normal(size=4)
            steps = np.full(4, t, dtype=np.uint64)
            out += engine.probe(handle, *convert(steps, actions, [t == 0] * 4, scales))
            out.append(engine.report(handle, convert(steps, q, None, None)[0], q))
        return out

    want = run(lambda s, a, e, c: (s, a, np.asarray(e), c))
    variants = [
        lambda s, a, e, c: (s.tolist(), a.tolist(), e, None if c is None else c.tolist()),
        lambda s, a, e, c: (s.astype(np.int64), a.astype(np.float32), e, c),
        lambda s, a, e, c: (s, np.asfortranarray(a), np.asarray(e), c),
        lambda s, a, e, c: (s.astype(np.uint32), np.ravel(a), None if e is None else np.int8(e), c),
    ]
    for convert in variants:
        for got, expected in zip(run(convert), want, strict=True):
            assert_bits_equal(got, expected)


def test_argument_type_errors(make_config):
    engine = Engine()
    config = make_config(np.random.default_rng(1), 1)
    handle = engine.resolve([engine.create_session("a", config_bytes(config))])
    with pytest.raises(ValueError, match="steps: expected integers >= 0"):
        engine.probe(handle, np.array([-1]), np.zeros(1))
    with pytest.raises(TypeError, match="steps"):
        engine.probe(handle, np.array([0.5]), np.zeros(1))
    with pytest.raises(ValueError):
        engine.probe(handle, [0], ["not a number"])
    with pytest.raises(TypeError):
        engine.probe("not a handle", [0], np.zeros(1))
    with pytest.raises(EngineError) as err:
        engine.create_session("b", b"\xff\xff")
    assert (err.value.code, err.value.index) == (INVALID_ARGUMENT, None)
    assert err.value.message.startswith("config: expected an encoded esa.v1.SessionConfig")
    assert len(engine) == 1


def test_fused_step_tracks_steps_in_place_and_refuses_bad_ones(make_config):
    """step_closed_form advances the tracked steps it is given, and only when it applies."""
    engine = Engine()
    config = make_config(np.random.default_rng(1), 1)
    handle = engine.resolve(
        [engine.create_session(f"s{i}", config_bytes(config)) for i in range(2)]
    )
    gain, offset, actions = np.ones(2), np.zeros(2), np.zeros((2, 1))

    def step(steps, starts=(False, False)):
        return engine.step_closed_form(
            handle, steps, actions, np.array(starts), None, gain, offset, False
        )

    steps = np.array([7, 9], np.int64)  # episode starts step at 0 whatever is tracked
    step(steps, (True, True))
    step(steps)
    assert steps.tolist() == [2, 2]
    before = [engine.get_session(f"s{i}") for i in range(2)]
    read_only = steps.copy()
    read_only.flags.writeable = False
    with pytest.raises(ValueError, match="steps: .*not writeable"):
        step(read_only)
    with pytest.raises(ValueError, match="steps: expected integers >= 0, got -1"):
        step(np.array([2, -1], np.int64))
    with pytest.raises(TypeError, match="steps"):
        step(steps.astype(np.uint64))
    assert [engine.get_session(f"s{i}") for i in range(2)] == before
    assert steps.tolist() == [2, 2]


def test_handles_and_errors_are_plain_python_objects(make_config):
    engine = Engine()
    config = make_config(np.random.default_rng(1), 2)
    ids = [engine.create_session(None, config_bytes(config)) for _ in range(3)]
    handle = engine.resolve(ids)
    assert isinstance(handle, BatchHandle)
    assert handle.ids == ids and len(handle) == 3
    assert repr(engine) == "Engine(live=3, max_sessions=100000)"
    with pytest.raises(EngineError) as err:
        engine.probe(handle, [1, 0, 0], np.zeros((3, 2)))
    assert (err.value.code, err.value.index) == (FAILED_PRECONDITION, 0)
    assert str(err.value) == err.value.message == "item 0: step mismatch: expected step 0, got 1"
    assert isinstance(err.value, Exception)
    import pickle

    again = pickle.loads(pickle.dumps(err.value))
    assert (again.code, again.index, again.message) == (
        err.value.code,
        err.value.index,
        err.value.message,
    )


def test_concurrent_threads_share_an_engine(make_config):
    """Threads stepping their own sessions of one engine (large batches release the GIL) get
    the results of running alone, and never deadlock."""
    rng = np.random.default_rng(6)
    configs = [make_config(rng, 64) for _ in range(96)]  # 6144 values: above DETACH_VALUES

    def script(engine, ids, seed, out):
        handle = engine.resolve(ids)
        rng = np.random.default_rng(seed)
        steps = np.zeros(len(ids), dtype=np.uint64)
        for t in range(30):
            probes, applied = engine.probe(handle, steps, rng.normal(size=(len(ids), 64)))
            out.append(engine.report(handle, steps, probes[:, 0] - applied[:, 1]))
            steps += 1
            if t % 10 == 0:
                engine.get_session(ids[0])

    alone = []
    for k in range(2):
        engine = Engine()
        ids = [engine.create_session(f"{k}-{i}", config_bytes(c)) for i, c in enumerate(configs)]
        result = []
        script(engine, ids, k, result)
        alone.append(result)
    engine = Engine()
    groups = [
        [engine.create_session(f"{k}-{i}", config_bytes(c)) for i, c in enumerate(configs)]
        for k in range(2)
    ]
    together = [[], []]
    threads = [
        threading.Thread(target=script, args=(engine, groups[k], k, together[k])) for k in range(2)
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=60)
        assert not thread.is_alive(), "deadlock"
    for got, want in zip(together, alone, strict=True):
        assert len(got) == len(want) == 30
        for g, w in zip(got, want, strict=True):
            assert_bits_equal(g, w)
