"""Riding out a lost server or lost sessions, for every batch and stepper.

A retried call sends only what the server has not applied (CONTRACT.md section 2, "Retries
are safe") and recreates lost sessions, which start a new episode.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TypeVar

import numpy as np
import numpy.typing as npt

from .errors import EsaError, SessionNotFound, StatusCode, StepMismatch
from .reconnect import Reconnect, RetriableErrors
from .state import BoolArray, F64Array, I64Array, SessionProgress, SessionState, check_array
from .transports.base import BatchTransport, Transport
from .transports.messages import BatchProbe, BatchReport

__all__ = ["Recovery", "StepLedger", "step_applied"]

_Answer = TypeVar("_Answer")


class StepLedger:
    """Where the ``n`` sessions of a batch (action dimension D) stand, as far as the client knows.

    Attributes:
        steps: The step each session's next probe (or pending report) carries, ``(N,)``;
            an in-process engine advances it in place.
        starts_due: Sessions whose next probe starts a new episode, ``(N,)``.
        deferred: A report held back to ride with the next probe, or None.
        last_probe: The last probe sent, replayed into recreated sessions before a lone report.
    """

    def __init__(self, n: int, action_dim: int) -> None:
        """A ledger of sessions at step 0."""
        self.n, self.action_dim = n, action_dim
        self.steps: I64Array = np.zeros(n, dtype=np.int64)
        self.starts_due: BoolArray = np.zeros(n, dtype=bool)
        self.deferred: BatchReport | None = None
        self.last_probe: BatchProbe | None = None

    def probe_inputs(
        self,
        actions: npt.ArrayLike,
        episode_starts: npt.ArrayLike | None,
        action_scales: npt.ArrayLike | None,
    ) -> tuple[F64Array, BoolArray, F64Array | None]:
        """The checked actions, episode starts (with those due) and action scales of a probe."""
        shape = (self.n, self.action_dim)
        a = check_array(actions, shape, "actions")
        starts = self.starts_due.copy()
        if episode_starts is not None:
            starts |= check_array(episode_starts, (self.n,), "episode_starts", dtype=bool)
        scales = None
        if action_scales is not None:
            scales = np.asarray(action_scales, np.float64)
            if scales.shape != shape:  # a scalar or a row, for every session
                scales = np.broadcast_to(scales, shape)
        return a, starts, scales

    def probe_request(
        self,
        actions: npt.ArrayLike,
        episode_starts: npt.ArrayLike | None,
        steps: npt.ArrayLike | None,
        action_scales: npt.ArrayLike | None,
    ) -> BatchProbe:
        """The checked probe of ``actions``, with the tracked steps unless ``steps`` is given."""
        a, starts, scales = self.probe_inputs(actions, episode_starts, action_scales)
        step = np.where(starts, 0, self.steps) if steps is None else np.array(steps, np.int64)
        return BatchProbe(step, a, starts, scales)

    def probed(self, request: BatchProbe) -> None:
        """Counts ``request`` as probed: its reports are due next."""
        self.steps = request.steps
        self.last_probe = request
        self.starts_due[:] = False

    def stepped(self, request: BatchProbe) -> None:
        """Counts a whole step (probe and report) of ``request`` as sent."""
        self.probed(request)
        self.steps = request.steps + 1

    def restarted(self) -> None:
        """Every session starts a new episode at its next probe; a deferred report is gone."""
        self.deferred = None
        self.steps[:] = 0
        self.starts_due[:] = True


class Recovery:
    """The one layer that rides out a lost server and recreates lost sessions.

    The calls keep ``ledger`` up to date. ``reconnect`` None raises the wire's first error and
    recreates nothing; ``restore`` is the batch's ``restore`` (every episode restarts).
    """

    def __init__(
        self,
        transport: Transport,
        ids: Sequence[str],
        batch: BatchTransport,
        ledger: StepLedger,
        reconnect: Reconnect | None,
        restore: Callable[[], int],
    ) -> None:
        """Holds what the calls need."""
        self._transport, self._ids, self._batch = transport, tuple(ids), batch
        self._ledger, self.reconnect, self._restore = ledger, reconnect, restore

    def _run(self, attempt: Callable[[bool], _Answer]) -> _Answer:
        """``attempt(retrying)`` under the reconnect policy, or once (not retrying) without."""
        return attempt(False) if self.reconnect is None else self.reconnect.run(attempt)

    def probe(self, request: BatchProbe) -> tuple[BatchProbe, tuple[F64Array, F64Array]]:
        """Sends the ledger's deferred report, if any, then ``request``; returns what was sent."""
        deferred = self._ledger.deferred

        def attempt(retrying: bool) -> tuple[BatchProbe, tuple[F64Array, F64Array]]:
            report, sent = deferred, request
            try:
                if retrying:
                    report, sent = self._reconcile(deferred, request)
                if report is None:
                    return sent, self._batch.probe(sent)
                return sent, self._batch.report_then_probe(report, sent)
            except SessionNotFound:
                if not retrying:
                    raise
                return self.restart(sent, self._batch.probe)

        return self._run(attempt)

    def report(self, request: BatchReport) -> tuple[BatchReport, F64Array]:
        """Sends a lone report; returns what was sent and the improved actions.

        The last probe is replayed into recreated sessions as an episode start.
        """

        def attempt(retrying: bool) -> tuple[BatchReport, F64Array]:
            try:
                return request, self._batch.report(request)
            except SessionNotFound:
                if not retrying or self._ledger.last_probe is None:
                    raise
            probe, _ = self.restart(self._ledger.last_probe, self._batch.probe)
            sent = request._replace(steps=probe.steps)
            return sent, self._batch.report(sent)

        return self._run(attempt)

    def send_ahead(
        self, request: BatchProbe, send: Callable[[BatchProbe], _Answer]
    ) -> tuple[BatchProbe, _Answer]:
        """``send(request)``, a step sent ahead; a failed send restarts every episode."""
        try:
            return request, send(request)
        except RetriableErrors:
            if self.reconnect is None:
                raise
            return self.reconnect.run(lambda _: self.restart(request, send))

    def receive_ahead(
        self,
        receive: Callable[[], F64Array],
        resume: Callable[[], F64Array],
        undo: Callable[[], None],
    ) -> F64Array:
        """``receive()``, the answer of a step sent ahead; ``resume()`` after a broken exchange.

        ``undo`` puts the ledger back before a step the server refused.
        """
        try:
            return receive()
        except RetriableErrors:
            if self.reconnect is None:
                self._ledger.starts_due[:] = True
                self._ledger.steps[:] = 0
                raise
        except EsaError:
            undo()
            raise
        return self.reconnect.run(lambda _: resume())

    def resume_ahead(
        self,
        sent: BatchProbe,
        steps_before: I64Array,
        seen: list[SessionProgress] | None,
        resend: Callable[[], F64Array],
    ) -> F64Array:
        """The shifts ``v(t + 1)`` of the step ``sent`` ahead whose answer the wire lost.

        Applied (:func:`step_applied`): the sessions' shifts; not applied: ``resend()``'s;
        otherwise every episode restarts, shifts 0.
        """
        try:
            states = [self._transport.get_session(i) for i in self._ids]
        except SessionNotFound:
            states = []
        applied = step_applied(states, sent, steps_before, seen) if states else None
        if applied:
            return np.stack([state.shift for state in states])
        if applied is False:
            try:
                return resend()
            except RetriableErrors:
                raise
            except EsaError:
                pass  # refused after all: the sessions restart below
        self._restore()
        return np.zeros((self._ledger.n, self._ledger.action_dim))

    def rerun_lost(
        self, run: Callable[[BoolArray | None], _Answer], episode_starts: BoolArray
    ) -> _Answer:
        """``run(episode_starts)``; after a lost session, recreates them and ``run(None)``."""
        try:
            return run(episode_starts)
        except SessionNotFound:
            self._restore()
            return run(None)

    def restart(
        self, request: BatchProbe, send: Callable[[BatchProbe], _Answer]
    ) -> tuple[BatchProbe, _Answer]:
        """Recreates lost sessions and ``send``s ``request`` as every session's episode start."""
        self._restore()
        restart = request._replace(
            steps=np.zeros(self._ledger.n, dtype=np.int64),
            episode_starts=np.ones(self._ledger.n, dtype=bool),
        )
        answer = send(restart)
        self._ledger.starts_due[:] = False
        self._ledger.last_probe = restart
        return restart, answer

    def _reconcile(
        self, deferred: BatchReport | None, request: BatchProbe
    ) -> tuple[BatchReport | None, BatchProbe]:
        """What is left to send of ``deferred`` and ``request`` after a broken exchange."""
        states = [self._transport.get_session(i) for i in self._ids]
        starts = request.episode_starts.copy()
        for i, state in enumerate(states):
            if starts[i] and state.step == 0 and state.probe_pending:
                # This episode-start probe was applied (with the report before it): replacing
                # it ends no further episode. (After a report of step 0 the state cannot tell;
                # the report is then dropped: at most one update of the mean square skipped.)
                starts[i] = False
                continue
            if deferred is None:
                continue
            step = int(deferred.steps[i])
            if state.step == step + 1:
                continue  # the report was applied (and maybe the probe after it)
            if state.step == step and state.probe_pending:
                references = deferred.q_references
                reference = None if references is None else float(references[i])
                self._transport.report(self._ids[i], step, float(deferred.q_values[i]), reference)
                continue
            raise StepMismatch(
                f"session {self._ids[i]!r} is at step {state.step} (probe pending: "
                f"{state.probe_pending}) after a broken exchange, expected step {step} or "
                f"{step + 1}",
                StatusCode.FAILED_PRECONDITION,
                index=i,
            )
        return None, request._replace(episode_starts=starts)


def step_applied(
    states: list[SessionState],
    sent: BatchProbe,
    steps_before: I64Array,
    seen: list[SessionProgress] | None,
) -> bool | None:
    """Whether the server applied the step ``sent`` ahead, from its sessions' states now.

    Applied: each session is at the step after the one sent, no probe pending; not applied:
    at ``steps_before``. After a one-step episode the two coincide and the episode count
    against ``seen`` decides. None when the states fit neither, or do not agree.
    """
    verdicts: set[bool] = set()
    for i, state in enumerate(states):
        after, before = int(sent.steps[i]) + 1, int(steps_before[i])
        if state.probe_pending or state.step not in (after, before):
            return None
        if after != before:
            verdicts.add(state.step == after)
            continue
        if seen is None:
            return None
        episodes = seen[i].episodes_completed
        if state.episodes_completed not in (episodes, episodes + 1):
            return None
        verdicts.add(state.episodes_completed == episodes + 1)
    return verdicts.pop() if len(verdicts) == 1 else None
