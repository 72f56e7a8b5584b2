"""How :meth:`~esa_client.SessionBatch.step` runs on each transport, with the same bits.

Each :class:`~esa_client.transports.base.BatchTransport` chooses its :class:`Stepper`
(:class:`FusedStepper` in-process, :class:`AheadStepper` on a gRPC StepStream), so a batch
never asks which transport it holds. A stepper is the batch's own step kept beside the
wires that choose it, so it reads and sets the batch's step counters directly (what it uses
of the batch is :class:`SessionBatch` here).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple, Protocol, TypeVar

import numpy as np
import numpy.typing as npt

from .._native import EngineError, StepAhead
from ..config import SessionConfig
from ..errors import EsaError, SessionNotFound, TypedErrors
from ..reconnect import Reconnect, RetriableErrors
from ..state import BoolArray, F64Array, I64Array, SessionProgress, SessionState, check_array
from .messages import BatchProbe, LinearCritic, QuadraticCritic

Critic = Callable[[F64Array], npt.ArrayLike] | LinearCritic | QuadraticCritic
"""What :meth:`~esa_client.SessionBatch.step` scores the probes with."""

_ClosedForm = (LinearCritic, QuadraticCritic)
"""The critics an in-process engine evaluates itself."""

_engine_errors = TypedErrors(EngineError)

_Answer = TypeVar("_Answer")


class SessionBatch(Protocol):
    """What a stepper uses of the :class:`~esa_client.SessionBatch` it steps."""

    n: int
    action_dim: int
    ids: tuple[str, ...]
    configs: tuple[SessionConfig, ...]
    _steps: I64Array
    _next_starts: BoolArray
    _reconnect: Reconnect | None

    def probe_applied(
        self,
        actions: npt.ArrayLike,
        episode_starts: npt.ArrayLike | None,
        *,
        action_scales: npt.ArrayLike | None,
    ) -> tuple[F64Array, F64Array]:
        """The probes and the actions to apply."""

    def report(
        self, q_values: npt.ArrayLike, *, q_references: npt.ArrayLike | None, defer: bool
    ) -> F64Array | None:
        """Reports the critic's values."""

    def flush(self) -> None:
        """Reads a step in flight and sends a deferred report."""

    def restore(self) -> int:
        """Recreates lost sessions; every session starts a new episode."""

    def states(self) -> list[SessionState]:
        """Each session's state on its server."""

    def _probe_request(
        self,
        actions: npt.ArrayLike,
        episode_starts: npt.ArrayLike | None,
        steps: npt.ArrayLike | None,
        action_scales: npt.ArrayLike | None,
    ) -> BatchProbe: ...

    def _probe_inputs(
        self,
        actions: npt.ArrayLike,
        episode_starts: npt.ArrayLike | None,
        action_scales: npt.ArrayLike | None,
    ) -> tuple[F64Array, BoolArray, F64Array | None]: ...

    def _sent(self, request: BatchProbe) -> None: ...

    def _restart(
        self, request: BatchProbe, send: Callable[[BatchProbe], _Answer]
    ) -> tuple[BatchProbe, _Answer]: ...


class StepCall(NamedTuple):
    """The arguments of one :meth:`~esa_client.SessionBatch.step`, as it documents them."""

    actions: npt.ArrayLike
    critic: Critic
    episode_starts: npt.ArrayLike | None
    action_scales: npt.ArrayLike | None
    paired: bool
    want_probes: bool


class Stepper:
    """A step as its round trips: the probe waits, and the report rides with the next probe."""

    def step(self, batch: SessionBatch, call: StepCall) -> tuple[F64Array | None, F64Array]:
        """One step of ``batch`` (see :meth:`~esa_client.SessionBatch.step`)."""
        check_critic(call.critic, batch.n, batch.action_dim)
        probes, applied = batch.probe_applied(
            call.actions, call.episode_starts, action_scales=call.action_scales
        )
        q = np.asarray(call.critic(np.concatenate([probes, applied]) if call.paired else probes))
        references = q[batch.n :] if call.paired else None
        batch.report(q[: batch.n], q_references=references, defer=True)
        return probes, applied

    def flush(self, batch: SessionBatch) -> None:
        """Reads the answer of a step in flight, raising its error (none here)."""

    def reset(self) -> None:
        """Forgets a step in flight: the batch's sessions start new episodes (none here)."""


class FusedBatch(Protocol):
    """A batch whose engine runs a whole step in one call: the in-process engine's."""

    def step_closed_form(
        self,
        steps: I64Array,
        inputs: tuple[F64Array, BoolArray, F64Array | None],
        critic: LinearCritic | QuadraticCritic,
        paired: bool,
    ) -> tuple[F64Array, F64Array]:
        """ProbeBatch, then ReportBatch of ``critic`` at the probes, in one engine call.

        ``steps`` are the tracked steps (an episode start steps at 0), advanced in place when
        the step is applied; ``inputs`` are the probe's actions, episode starts and scales. A
        quadratic critic is evaluated at the clipped probes. With ``paired``, the critic at
        the applied actions is reported as the references. Returns the probes and the applied
        actions.
        """


class FusedStepper(Stepper):
    """A step in one engine call for a linear or quadratic critic; round trips for others."""

    def __init__(self, fused: FusedBatch) -> None:
        """Steps through ``fused``'s engine calls."""
        self._fused = fused

    def step(self, batch: SessionBatch, call: StepCall) -> tuple[F64Array | None, F64Array]:
        """One engine call (see :meth:`~esa_client.SessionBatch.step`)."""
        critic = call.critic
        if not isinstance(critic, _ClosedForm):
            return super().step(batch, call)
        batch.flush()
        # In this process: no wire to ride out, so no reconnect around the call (nor a probe
        # to replay into recreated sessions), and the engine advances the steps itself.
        inputs = batch._probe_inputs(call.actions, call.episode_starts, call.action_scales)
        try:
            answer = self._fused.step_closed_form(batch._steps, inputs, critic, call.paired)
        except ValueError:
            # esa-core checks the critic itself, all or nothing; checking it here first too
            # would cost more than the step. A refusal is told in the words of every transport.
            check_critic(critic, batch.n, batch.action_dim)
            raise
        batch._next_starts.fill(False)
        return answer


class AheadBatch(Protocol):
    """A batch that sends a whole step and reads its answer later, in the order sent.

    The wire's ``step_linear_batch`` and ``step_batch`` (CONTRACT.md section 1b,
    implementation note 8), answered with the shifts ``v(t + 1)``.
    """

    def send_step_linear(self, request: BatchProbe, critic: LinearCritic, paired: bool) -> None:
        """Sends the step for a linear critic; returns once it is on its way."""

    def send_step(
        self, request: BatchProbe, q_values: F64Array, q_references: F64Array | None
    ) -> None:
        """Sends the step with the critic's values at its probes; returns once it is on its way."""

    def receive_step(self) -> tuple[F64Array, F64Array, F64Array]:
        """The oldest unanswered step's ``(probes, applied, shifts)``, each ``(N, D)``.

        Raises the step's error (nothing of it was applied), or the wire's (whether it
        was applied is then unknown).
        """

    def resend_step(self) -> None:
        """Sends the step whose answer the wire lost again; ``receive_step`` reads its answer."""

    def progress(self) -> list[SessionProgress] | None:
        """Each session's progress in the last answer read (None before one)."""

    def close(self) -> None:
        """Ends the stream; the next step starts a new one."""


class _InFlight(NamedTuple):
    """A step sent ahead: what it replaced, restored if it fails, and what it sent."""

    steps_before: I64Array
    starts_before: BoolArray
    request: BatchProbe


class AheadStepper(Stepper):
    """A step sent ahead of its answer, unless the caller waits for its probes.

    The applied actions, and the probes for a critic evaluated here (the server evaluates a
    ``LinearCritic`` itself), are computed with esa-core's own function from the shifts
    ``v(t)`` of the previous step's answer (0 at an episode start); the step goes as one
    message whose answer is read at the next call, overlapping the env's and learner's work.
    """

    def __init__(self, ahead: AheadBatch) -> None:
        """Sends steps through ``ahead``."""
        self._ahead = ahead
        self._in_flight: _InFlight | None = None
        # The shifts v(t) of the next step, from the last answer read.
        self._shifts: F64Array | None = None
        self._engine: StepAhead | None = None

    def step(self, batch: SessionBatch, call: StepCall) -> tuple[F64Array | None, F64Array]:
        """The step sent ahead (see :meth:`~esa_client.SessionBatch.step`)."""
        if call.want_probes:
            return super().step(batch, call)
        critic, paired = call.critic, call.paired
        check_critic(critic, batch.n, batch.action_dim)
        batch.flush()
        request = batch._probe_request(call.actions, call.episode_starts, None, call.action_scales)
        steps_before, starts_before = batch._steps, batch._next_starts.copy()
        try:
            applied = self._send(batch, request, critic, paired)
        except RetriableErrors:
            if batch._reconnect is None:
                raise
            request, applied = batch._reconnect.run(
                lambda _: batch._restart(
                    request, lambda restart: self._send(batch, restart, critic, paired)
                )
            )
        self._in_flight = _InFlight(steps_before, starts_before, request)
        batch._sent(request)
        return None, applied

    def flush(self, batch: SessionBatch) -> None:
        """Reads the answer of the step in flight (raising its error), if there is one."""
        if self._in_flight is not None:
            self._shifts = self._receive(batch)

    def reset(self) -> None:
        """Forgets the step in flight (its answer would be read as the next step's)."""
        if self._in_flight is not None:
            self._in_flight = None
            self._ahead.close()
        self._shifts = None

    def _send(
        self, batch: SessionBatch, request: BatchProbe, critic: Critic, paired: bool
    ) -> F64Array:
        """Sends ``request``'s step, computed from the shifts in hand; returns its actions.

        The actions and scales (and a critic's values) are checked before anything is sent:
        an error there is this call's.
        """
        if self._engine is None:
            self._engine = StepAhead([c.to_proto().SerializeToString() for c in batch.configs])
        shifts = self._shifts
        if shifts is None:
            shifts = np.zeros((batch.n, batch.action_dim))
        if request.episode_starts.any():
            shifts = np.where(request.episode_starts[:, None], 0.0, shifts)
        if isinstance(critic, LinearCritic):
            # The server evaluates it (step_linear_batch).
            with _engine_errors:
                applied: F64Array = self._engine(shifts, request.actions, request.action_scales)
            self._ahead.send_step_linear(request, critic, paired)
            return applied
        with _engine_errors:
            probes, applied = self._engine.probes(
                shifts, request.steps, request.actions, request.action_scales
            )
        points = np.concatenate([probes, applied]) if paired else probes
        q = check_array(critic(points), (len(points),), "critic values", finite=True)
        self._ahead.send_step(request, q[: batch.n], q[batch.n :] if paired else None)
        return applied

    def _receive(self, batch: SessionBatch) -> F64Array:
        """The shifts ``v(t + 1)`` of the step in flight, or its error.

        A refused step is undone here (its steps and episode starts are due again); after a
        broken exchange a reconnect policy rides out the server's absence and continues where
        the server is (:meth:`_resume`); without one every session restarts.
        """
        assert self._in_flight is not None
        sent, self._in_flight = self._in_flight, None
        try:
            return self._ahead.receive_step()[2]
        except RetriableErrors:
            if batch._reconnect is None:
                batch._next_starts[:] = True
                batch._steps[:] = 0
                raise
        except EsaError:
            batch._steps = sent.steps_before
            batch._next_starts = sent.starts_before
            raise
        return batch._reconnect.run(lambda _: self._resume(batch, sent))  # restart hook

    def _resume(self, batch: SessionBatch, sent: _InFlight) -> F64Array:
        """The shifts ``v(t + 1)`` of the step sent ahead whose answer the wire lost.

        The sessions' states tell whether the server applied the step (:func:`_step_applied`):
        if it did, the shifts are theirs; if not, the same step goes again and its answer
        gives them. When the server lost the sessions, or their states fit neither case,
        every session restarts its episode (:meth:`~esa_client.SessionBatch.restore`) and the
        shifts are 0. Errors of the wire propagate, for the reconnect policy to retry.
        """
        try:
            states = batch.states()
        except SessionNotFound:
            states = []
        applied = None
        if states:
            applied = _step_applied(states, sent, self._ahead.progress())
        if applied:
            return np.stack([state.shift for state in states])
        if applied is False:
            self._ahead.resend_step()
            try:
                return self._ahead.receive_step()[2]
            except RetriableErrors:
                raise
            except EsaError:
                pass  # refused after all: the sessions restart below
        batch.restore()
        return np.zeros((batch.n, batch.action_dim))


def _step_applied(
    states: list[SessionState], sent: _InFlight, seen: list[SessionProgress] | None
) -> bool | None:
    """Whether the server applied the step ``sent`` ahead, from its sessions' states now.

    Applied, each session is at the step after the one sent with no probe pending; not
    applied, at its step before. The two coincide only for an episode start right after a
    one-step episode: then the episode count tells them apart, against the count ``seen`` in
    the answer before. None when the states fit neither, or do not agree (a step is applied
    to all its sessions or to none).
    """
    verdicts: set[bool] = set()
    for i, state in enumerate(states):
        after, before = int(sent.request.steps[i]) + 1, int(sent.steps_before[i])
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


def check_critic(critic: Critic, n: int, dim: int) -> None:
    """Checks a linear or quadratic critic for ``n`` sessions of dimension ``dim``.

    Raises:
        ValueError: A shape is wrong, or a quadratic critic's coefficient not finite, a
            curvature positive, or a bound NaN or a low above its high.
    """
    if not isinstance(critic, _ClosedForm):
        return
    shape = (n, dim)
    if isinstance(critic, LinearCritic):
        shapes = [np.shape(critic.gain), np.shape(critic.offset)]
        if shapes != [shape, (n,)]:
            raise ValueError(
                f"critic: expected gain of shape {shape} and offset of shape {(n,)}, "
                f"got {shapes[0]} and {shapes[1]}"
            )
        return
    shapes = [np.shape(part) for part in critic[:3]]
    if shapes != [shape, shape, (n,)]:
        raise ValueError(
            f"critic: expected gain and curvature of shape {shape} and offset of shape {(n,)}, "
            f"got {shapes[0]}, {shapes[1]} and {shapes[2]}"
        )
    for name, values in zip(("gain", "curvature", "offset"), critic[:3], strict=True):
        if not np.all(np.isfinite(values)):
            raise ValueError(f"critic: expected a finite {name}, got {values!r}")
    if np.any(np.asarray(critic.curvature) > 0):
        raise ValueError(f"critic: expected curvature <= 0, got {critic.curvature!r}")
    low, high = critic.low, critic.high
    if low is None or high is None:
        if low is not None or high is not None:
            raise ValueError(f"critic: expected both bounds or neither, got {low!r} and {high!r}")
        return
    bounds = (np.shape(low), np.shape(high))
    if bounds != ((dim,), (dim,)):
        raise ValueError(
            f"critic: expected low and high of shape {(dim,)}, got {bounds[0]} and {bounds[1]}"
        )
    if not np.all(np.asarray(low) <= np.asarray(high)):
        raise ValueError(f"critic: expected low <= high (no NaN), got {low!r} and {high!r}")
