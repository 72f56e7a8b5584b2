"""The in-process transport and the real server answer the same calls identically, bit for bit.

The same scripts run through ``EsaClient.in_process()`` and through the session-scoped gRPC
``client`` (the same ids on both sides: they share nothing), over random configs with every
CONTRACT.md section 1b field: unary sessions, batches with and without a stream, action scales,
paired references and deferred reports. Every bad input raises the same exception type, status
code, failing item and message on both sides, and leaves both in the same state.
"""

import importlib.util
import math
import uuid
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from esa_client import (
    EsaClient,
    EsaError,
    InvalidArgument,
    LinearCritic,
    ResourceExhausted,
    SessionAlreadyExists,
    SessionConfig,
    SessionNotFound,
    StatusCode,
    StepMismatch,
)
from esa_client._native import Engine
from esa_client._proto.esa.v1 import esa_pb2
from esa_client.transports.in_process import InProcessTransport


def sibling(name: str) -> ModuleType:
    """Another test module of this folder, for its helpers (``--import-mode=importlib`` keeps
    the folder off ``sys.path``)."""
    spec = importlib.util.spec_from_file_location(
        f"_inprocess_{name}", Path(__file__).with_name(f"{name}.py")
    )
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


assert_bits_equal = sibling("test_native").assert_bits_equal
_bounded_law = sibling("test_bounded_law")
landscape, run_batch = _bounded_law.landscape, _bounded_law.run_batch
_zenoh_parity = sibling("test_zenoh_parity")
session_script, batch_script = _zenoh_parity.session_script, _zenoh_parity.batch_script


@pytest.fixture
def local():
    """A fresh in-process client per test."""
    with EsaClient.in_process() as c:
        yield c


def assert_all_bits_equal(left, right):
    assert len(left) == len(right)
    for a, b in zip(left, right, strict=True):
        assert np.shape(a) == np.shape(b)
        assert_bits_equal(a, b)


def assert_states_identical(left, right):
    """Snapshots agree exactly: config, counters, shift and mean square bit for bit."""
    for a, b in zip(left, right, strict=True):
        assert a.config == b.config
        assert (a.step, a.episodes_completed, a.probe_pending) == (
            b.step,
            b.episodes_completed,
            b.probe_pending,
        )
        assert_bits_equal(a.shift, b.shift)
        assert (a.response_mean_square is None) == (b.response_mean_square is None)
        if a.response_mean_square is not None:
            assert_bits_equal(a.response_mean_square, b.response_mean_square)


def unary_1b_script(client, session_id, config, seed):
    """Probes with scales, reports with references, retries and episode ends; every answer."""
    rng = np.random.default_rng(seed)
    session = client.create_session(config, session_id)
    out = []
    for episode in range(4):
        for t in range(int(rng.integers(10, 30))):
            scale = rng.uniform(0.05, 2.0, config.action_dim) if rng.random() < 0.7 else None
            action = rng.normal(size=config.action_dim)
            probe, applied = session.probe_applied(action, episode_start=t == 0, action_scale=scale)
            if rng.random() < 0.15:  # a retry of the same step replaces the pending probe
                probe, applied = session.probe_applied(
                    rng.normal(size=config.action_dim), step=session.step, action_scale=scale
                )
            level = rng.uniform(-3, 3)
            reference = float(landscape(applied, level)) if rng.random() < 0.5 else None
            improved = session.report(float(landscape(probe, level)), q_reference=reference)
            out += [probe, applied, improved]
            if rng.random() < 0.15:  # a replay of the step just applied answers it again
                out.append(session.report(0.0, step=session.step - 1))
        if episode % 2:
            out.append(np.array([session.end_episode()]))
    states = [session.state()]
    session.close()
    return out, states


@pytest.mark.parametrize("seed", range(6))
def test_unary_scripts_are_identical(client, local, make_config, seed):
    config = make_config(np.random.default_rng(seed))
    session_id = f"inproc-unary-{seed}-{uuid.uuid4()}"
    remote, remote_states = unary_1b_script(client, session_id, config, seed)
    here, here_states = unary_1b_script(local, session_id, config, seed)
    assert_all_bits_equal(here, remote)
    assert_states_identical(here_states, remote_states)
    config = make_config(np.random.default_rng(50 + seed))
    assert_all_bits_equal(
        session_script(local, session_id, config, seed),
        session_script(client, session_id, config, seed),
    )


@pytest.mark.parametrize("defer", [False, True], ids=["sequential", "pipelined"])
@pytest.mark.parametrize("use_stream", [False, True], ids=["batch", "stream"])
@pytest.mark.parametrize("seed", range(3))
def test_batch_scripts_are_identical(client, local, make_config, seed, use_stream, defer):
    rng = np.random.default_rng(700 + seed)
    n, d = int(rng.integers(1, 9)), int(rng.integers(1, 5))
    configs = [make_config(rng, d) for _ in range(n)]
    ids = [f"inproc-batch-{seed}-{i}-{uuid.uuid4()}" for i in range(n)]
    answers, states = [], []
    for side in (client, local):
        batch = side.create_batch(configs, ids=ids, use_stream=use_stream)
        answers.append(run_batch(batch, np.random.default_rng(seed), n, d, 100, defer))
        states.append(batch.states())
        batch.close()
    assert_all_bits_equal(answers[1], answers[0])
    assert_states_identical(states[1], states[0])
    more = [f"inproc-script-{seed}-{i}-{uuid.uuid4()}" for i in range(5)]
    assert_all_bits_equal(
        batch_script(local, more, configs[0], seed, use_stream),
        batch_script(client, more, configs[0], seed, use_stream),
    )


CONFIG = SessionConfig(action_dim=2, dt=0.05, amplitude=0.2, frequency=10.0, learning_rate=0.5)


class Sides:
    """The same sessions and batch on both sides, started one step in, and the outcome of
    running a bad call on each."""

    def __init__(self, client, local, use_stream):
        self.ids = [f"inproc-bad-{i}-{uuid.uuid4()}" for i in range(3)]
        self.sides = {}
        for name, side in (("server", client), ("local", local)):
            batch = side.create_batch(CONFIG, 3, ids=self.ids, use_stream=use_stream)
            batch.probe(np.zeros((3, 2)), [True] * 3, action_scales=0.5)
            batch.report([1.0, 2.0, 3.0])
            batch.probe(np.full((3, 2), 0.1))
            session = side.create_session(CONFIG, f"{self.ids[0]}-one")
            session.probe([0.1, 0.2], episode_start=True)
            self.sides[name] = (side, batch, session)

    def states(self, name):
        side, batch, session = self.sides[name]
        return [*(side.session_state(i) for i in batch.ids), session.state()]

    def outcome(self, name, call):
        side, batch, session = self.sides[name]
        try:
            call(side, batch, session)
        except EsaError as err:
            # Messages agree where they say what to fix; a missing session's message names
            # what a server has and an engine has not (an idle expiry).
            worded = err.code in (
                StatusCode.INVALID_ARGUMENT,
                StatusCode.FAILED_PRECONDITION,
            )
            return type(err), err.code, err.index, err.message if worded else None
        except (ValueError, TypeError, OverflowError) as err:  # refused before any call
            return type(err), None, None, None
        return None


NAN2 = np.array([[0.0, 0.0], [0.0, 0.0], [0.0, math.nan]])
BAD_CALLS = {
    "probe NaN item": lambda c, b, s: b.probe(NAN2),
    "probe inf": lambda c, b, s: b.probe(np.full((3, 2), math.inf)),
    "probe zero scale": lambda c, b, s: b.probe(np.zeros((3, 2)), action_scales=[0.1, 0.0]),
    "probe negative scale item": lambda c, b, s: b.probe(
        np.zeros((3, 2)), action_scales=np.array([[1, 1], [-1, 1], [1, 1]])
    ),
    "probe step mismatch": lambda c, b, s: b.probe(np.zeros((3, 2)), steps=[1, 2, 1]),
    "probe step too early": lambda c, b, s: b.probe(np.zeros((3, 2)), steps=[1, 1, 0]),
    "negative steps": lambda c, b, s: b.probe(np.zeros((3, 2)), steps=[1, -1, 1]),
    "probe wrong step count": lambda c, b, s: b.probe(np.zeros((3, 2)), steps=[1, 1]),
    "report NaN item": lambda c, b, s: b.report([1.0, math.nan, 1.0]),
    "report inf reference": lambda c, b, s: b.report([1.0] * 3, q_references=[0, 0, -math.inf]),
    "report step mismatch": lambda c, b, s: b.report([1.0] * 3, steps=[1, 3, 1]),
    "report without probe": lambda c, b, s: b.report([1.0] * 3, steps=[2, 2, 2]),
    "deferred bad report": lambda c, b, s: (
        b.report([math.nan] * 3, defer=True),
        b.probe_applied(np.zeros((3, 2))),
    ),
    "unary probe NaN": lambda c, b, s: s.probe([math.nan, 0.0]),
    "unary probe length": lambda c, b, s: s.probe([0.0]),
    "unary bad scale": lambda c, b, s: s.probe([0.0, 0.0], action_scale=[0.0, 1.0]),
    "unary step mismatch": lambda c, b, s: s.probe([0.0, 0.0], step=3),
    "unary negative step": lambda c, b, s: s.probe([0.0, 0.0], step=-1),
    "unary report NaN": lambda c, b, s: s.report(math.nan),
    "unary report inf reference": lambda c, b, s: s.report(1.0, q_reference=math.inf),
    "unary report wrong step": lambda c, b, s: s.report(1.0, step=4),
    "unknown session": lambda c, b, s: c.get_session("ghost"),
    "end unknown": lambda c, b, s: c.transport.end_episode("ghost"),
    "close unknown": lambda c, b, s: c.transport.close_session("ghost"),
    "long id": lambda c, b, s: c.create_session(CONFIG, "x" * 129),
    "empty id": lambda c, b, s: c.session_state(""),
    "same id other config": lambda c, b, s: c.create_session(
        SessionConfig(action_dim=2, dt=0.05, amplitude=0.3, frequency=10.0, learning_rate=0.5),
        s.id,
    ),
    "bad raw config": lambda c, b, s: c.create_session(esa_pb2.SessionConfig(action_dim=0)),
    "repeated id in batch": lambda c, b, s: c.create_batch(
        CONFIG, 2, ids=[f"{s.id}-twice"] * 2
    ).probe(np.zeros((2, 2))),
    "closed session in batch": lambda c, b, s: (
        c.transport.close_session(b.ids[1]),
        b.probe(np.zeros((3, 2))),
    ),
}


@pytest.mark.parametrize("use_stream", [False, True], ids=["batch", "stream"])
def test_bad_inputs_raise_alike_and_change_nothing(client, local, use_stream):
    sides = Sides(client, local, use_stream)
    for name, call in BAD_CALLS.items():
        before = {side: sides.states(side) for side in ("server", "local")}
        server, here = sides.outcome("server", call), sides.outcome("local", call)
        assert server is not None, f"{name}: the server accepted it"
        assert here == server, name
        if name == "closed session in batch":
            continue
        for side in ("server", "local"):
            assert_states_identical(sides.states(side), before[side])
        assert_states_identical(sides.states("local"), sides.states("server"))
    # After every refusal both sides carry on alike (the closed session restored).
    answers = []
    for side in ("server", "local"):
        _, batch, session = sides.sides[side]
        assert batch.restore() == 1
        answers += [session.report(1.0), batch.probe(np.zeros((3, 2)))]
    assert_all_bits_equal(answers[2:], answers[:2])


def test_the_session_limit_is_resource_exhausted(server_bin):
    with EsaClient.spawn(server_bin, max_sessions=2) as remote:
        local = EsaClient.in_process(max_sessions=2)
        for side in (remote, local):
            side.create_session(CONFIG, "a")
            side.create_session(CONFIG, "b")
            with pytest.raises(ResourceExhausted) as info:
                side.create_session(CONFIG, "c")
            assert info.value.code == StatusCode.RESOURCE_EXHAUSTED
            assert side.create_session(CONFIG, "a").id == "a"  # an existing one still answers
        with pytest.raises(SessionAlreadyExists):
            local.create_session(SessionConfig(1, 0.05, 0.2, 10.0, 0.1), "a")


def test_lost_sessions_are_restored_in_process(local):
    batch = local.create_batch(CONFIG, 2)
    batch.probe(np.zeros((2, 2)), [True, True])
    local.transport.close_session(batch.ids[0])
    with pytest.raises(SessionNotFound) as info:
        batch.report([1.0, 2.0])
    assert info.value.index == 0
    assert batch.restore() == 1 and local.sessions_restored == 1
    assert batch.probe(np.zeros((2, 2))).shape == (2, 2)
    with pytest.raises(StepMismatch):
        batch.report([1.0, 2.0], steps=[5, 0])


def test_a_step_leaves_the_callers_steps_alone(local):
    """The engine advances the batch's own step count in place, never an array it was given."""
    batch = local.create_batch(CONFIG, 2)
    given = np.zeros(2, np.int64)
    batch.probe(np.zeros((2, 2)), [True, True], steps=given)
    critic = LinearCritic(np.ones((2, 2)), np.zeros(2))
    for _ in range(3):  # the first replaces the pending probe of step 0
        batch.step(np.zeros((2, 2)), critic)
    assert given.tolist() == [0, 0] and batch.steps.tolist() == [3, 3]


def test_the_transport_takes_an_engine(make_config):
    engine = Engine(max_sessions=3)
    transport = InProcessTransport(engine)
    created = transport.create_session("", make_config(np.random.default_rng(0)).to_proto())
    assert uuid.UUID(created) and created in engine and transport.healthy(0.1)
    with pytest.raises(ValueError, match="both"):
        InProcessTransport(engine, max_sessions=2)
    with pytest.raises(InvalidArgument):
        transport.get_session("")
    client = EsaClient.in_process()
    assert repr(client) == "EsaClient('in-process', InProcessTransport())" and client.healthy()
    client.close()
    client.close()
