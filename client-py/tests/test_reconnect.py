"""Retries after a failure of the wire: the backoff, and no update applied twice or lost.

A wrapper around the in-process engine fails chosen round trips the ways a network does
(before the server saw the request, or after it applied it and the answer was lost, or
halfway through a pipelined report and probe); a batch stepped through it must end in
exactly the state of one stepped without failures: the same steps, episodes and shift,
bit for bit.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import pytest

from esa_client import EsaClient, SessionConfig
from esa_client.errors import DeadlineExceeded, InvalidArgument, ServerUnavailable, StatusCode
from esa_client.reconnect import Reconnect
from esa_client.session import SessionBatch
from esa_client.transports.base import BatchProbe, BatchReport, BatchTransport

CONFIG = SessionConfig(
    action_dim=2,
    dt=0.02,
    amplitude=0.2,
    frequency=[31.4, 15.7],
    learning_rate=0.3,
    normalize_response=True,
    trust_region=1.0,
)


def lost(what: str) -> ServerUnavailable:
    return ServerUnavailable(f"simulated: {what}", StatusCode.UNAVAILABLE)


class FlakyBatch(BatchTransport):
    """Fails the round trips that ``plan`` names: ``call number -> mode``."""

    def __init__(
        self, inner: BatchTransport, plan: dict[int, str], restart: Callable[[], None]
    ) -> None:
        self.inner, self.plan, self.calls, self.restart = inner, plan, 0, restart

    def _mode(self) -> str | None:
        self.calls += 1
        mode = self.plan.get(self.calls)
        if mode == "restart":
            self.restart()  # the server restarts: its sessions are gone
            raise lost("server restarting")
        return mode

    def probe(self, request: BatchProbe) -> tuple[np.ndarray, np.ndarray]:
        mode = self._mode()
        if mode == "before":
            raise lost("probe never arrived")
        answer = self.inner.probe(request)
        if mode is not None:
            raise lost("probe answer lost")
        return answer

    def report(self, request: BatchReport) -> np.ndarray:
        mode = self._mode()
        if mode == "before":
            raise lost("report never arrived")
        answer = self.inner.report(request)
        if mode is not None:
            raise lost("report answer lost")
        return answer

    def report_then_probe(
        self, report: BatchReport, probe: BatchProbe
    ) -> tuple[np.ndarray, np.ndarray]:
        mode = self._mode()
        if mode == "before":
            raise lost("pair never arrived")
        self.inner.report(report)
        if mode == "half":
            raise DeadlineExceeded(
                "simulated: stalled after the report", StatusCode.DEADLINE_EXCEEDED
            )
        answer = self.inner.probe(probe)
        if mode is not None:
            raise lost("pair answers lost")
        return answer

    def close(self) -> None:
        self.inner.close()


class FlakyTransport:
    """The in-process transport whose batches fail as ``plan`` says."""

    def __init__(self, inner: object, plan: dict[int, str]) -> None:
        self._inner, self._plan = inner, plan
        self.ids: Sequence[str] = ()

    def _restart(self) -> None:
        for session_id in self.ids:
            self._inner.close_session(session_id)  # type: ignore[attr-defined]

    def __getattr__(self, name: str) -> object:
        return getattr(self._inner, name)

    def open_batch(self, ids: Sequence[str], action_dim: int, *, use_stream: bool) -> FlakyBatch:
        inner = self._inner.open_batch(ids, action_dim, use_stream=use_stream)  # type: ignore[attr-defined]
        self.ids = ids
        return FlakyBatch(inner, self._plan, self._restart)


def train(batch: SessionBatch, steps: int, *, pipelined: bool) -> None:
    rng = np.random.default_rng(0)
    for t in range(steps):
        actions = rng.normal(size=(batch.n, 2))
        starts = np.full(batch.n, t % 7 == 0)
        probes, applied = batch.probe_applied(actions, starts)
        q = -np.sum((np.concatenate([probes, applied]) - 0.3) ** 2, axis=1)
        batch.report(q[: batch.n], q_references=q[batch.n :], defer=pipelined)
    batch.flush()


def final_states(batch: SessionBatch) -> list[tuple[int, int, bool, list[float]]]:
    return [
        (s.step, s.episodes_completed, s.probe_pending, s.shift.tolist()) for s in batch.states()
    ]


@pytest.mark.parametrize("pipelined", [True, False], ids=["pipelined", "in-turn"])
@pytest.mark.parametrize("mode", ["before", "after", "half"])
def test_a_retried_step_ends_where_an_undisturbed_one_does(mode, pipelined):
    steps = 30
    with EsaClient.in_process() as engine:
        clean = engine.create_batch(CONFIG, 3)
        train(clean, steps, pipelined=pipelined)
        # Every third round trip fails, including episode starts (every 7th step).
        plan = {call: mode for call in range(2, 2 * steps, 3)}
        flaky = SessionBatch(
            FlakyTransport(engine.transport, plan),  # type: ignore[arg-type]
            [f"flaky-{i}" for i in range(3)],
            [CONFIG] * 3,
            reconnect=Reconnect("in-process", 5.0, initial_backoff=0.001, max_backoff=0.002),
        )
        for session_id in flaky.ids:
            engine.transport.create_session(session_id, CONFIG.to_proto())
        train(flaky, steps, pipelined=pipelined)
        assert final_states(flaky) == final_states(clean)
        assert flaky.sessions_restored == 0


@pytest.mark.parametrize("pipelined", [True, False], ids=["pipelined", "in-turn"])
def test_sessions_a_restart_lost_are_recreated_and_the_step_replayed(pipelined):
    steps = 30
    with EsaClient.in_process() as engine:
        # Restarts on a probe (call 9) and, in turn, on a lone report (call 20).
        plan = {9: "restart", 20: "restart"}
        flaky = SessionBatch(
            FlakyTransport(engine.transport, plan),  # type: ignore[arg-type]
            [f"restart-{i}" for i in range(3)],
            [CONFIG] * 3,
            reconnect=Reconnect("in-process", 5.0, initial_backoff=0.001, max_backoff=0.002),
        )
        for session_id in flaky.ids:
            engine.transport.create_session(session_id, CONFIG.to_proto())
        train(flaky, steps, pipelined=pipelined)
        assert flaky.sessions_restored == 2 * 3
        states = flaky.states()
        assert [s.step for s in states] == flaky.steps.tolist()
        assert not any(s.probe_pending for s in states)


def test_backoff_doubles_with_jitter_up_to_the_cap_then_gives_up():
    pauses: list[float] = []
    attempts = 0

    def failing(retrying: bool) -> None:
        nonlocal attempts
        assert retrying == (attempts > 0)
        attempts += 1
        raise lost("down")

    policy = Reconnect("10.0.0.5:50051", 0.5, initial_backoff=0.01, max_backoff=0.04)
    with pytest.raises(ServerUnavailable, match=r"10\.0\.0\.5:50051.*gave up after") as info:
        policy.run(failing, sleep=lambda s: (pauses.append(s), __import__("time").sleep(s)))
    assert isinstance(info.value.__cause__, ServerUnavailable)
    caps = [min(0.01 * 2**i, 0.04) for i in range(len(pauses))]
    assert all(cap / 2 <= p <= cap for p, cap in zip(pauses[:-1], caps, strict=False))
    assert attempts == len(pauses) + 1


def test_no_retry_for_errors_of_the_request_or_with_a_zero_deadline():
    def invalid(retrying: bool) -> None:
        raise InvalidArgument("bad", StatusCode.INVALID_ARGUMENT)

    with pytest.raises(InvalidArgument):
        Reconnect("x", 10).run(invalid, sleep=pytest.fail)

    def down(retrying: bool) -> None:
        raise lost("down")

    with pytest.raises(ServerUnavailable, match="simulated"):
        Reconnect("x", 0).run(down, sleep=pytest.fail)
    with pytest.raises(ServerUnavailable, match="simulated"):
        Reconnect("x", 10, closed=lambda: True).run(down, sleep=pytest.fail)
