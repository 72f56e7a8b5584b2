"""Sessions on an esa server: one :class:`Session`, or a :class:`SessionBatch` for N envs.

Both track their sessions' step counters; a failed call changes none, so repeating it is
safe, except that an episode-start probe whose answer was lost ends one more (empty)
episode when repeated (it counts toward ``lr_decay`` and ``max_episodes``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import numpy.typing as npt

from .config import SessionConfig
from .errors import SessionNotFound
from .reconnect import Reconnect
from .recovery import Recovery, StepLedger
from .state import (
    F64Array,
    I64Array,
    SessionProgress,
    SessionState,
    as_batch_configs,
    check_array,
    check_indices,
)
from .transports.base import BatchReport, SessionProbe, Transport
from .transports.stepping import Critic, StepCall

__all__ = ["Session", "SessionBatch", "SessionProgress", "SessionState", "restore_sessions"]


def restore_sessions(
    transport: Transport,
    ids: Sequence[str],
    configs: SessionConfig | Sequence[SessionConfig],
    progress: Sequence[SessionProgress | None] | None = None,
) -> int:
    """Recreates the sessions ``transport`` lost; see :meth:`EsaClient.restore_sessions`."""
    per_session = as_batch_configs(configs, len(ids))
    if progress is not None and len(progress) != len(ids):
        raise ValueError(f"expected one progress per session id ({len(ids)}), got {len(progress)}")
    resumed = [None] * len(ids) if progress is None else progress
    restored = 0
    for session_id, config, seen in zip(ids, per_session, resumed, strict=True):
        try:
            transport.get_session(session_id)
        except SessionNotFound:
            if seen is not None:
                transport.resume_session(session_id, config.to_proto(), seen.to_proto())
            else:
                transport.create_session(session_id, config.to_proto())
            restored += 1
    return restored


class Session:
    """One ESA session; created by :meth:`EsaClient.create_session`.

    Its calls raise the wire's error at once; to ride out a lost server step a
    :class:`SessionBatch` (``create_batch(config, 1)``).
    """

    def __init__(
        self, transport: Transport, session_id: str, config: SessionConfig, step: int = 0
    ) -> None:
        """Binds to an existing session (use the client's factory methods)."""
        self._transport = transport
        self.id = session_id
        self.config = config
        self._step = step

    @property
    def step(self) -> int:
        """The step t the next probe (or pending report) carries."""
        return self._step

    def probe(
        self,
        action: npt.ArrayLike,
        *,
        episode_start: bool = False,
        step: int | None = None,
        action_scale: npt.ArrayLike | None = None,
    ) -> F64Array:
        """Sends the sampled action and returns the probe at which to evaluate Q.

        Args:
            action: The sampled action a_t, shape ``(action_dim,)``.
            episode_start: True on an episode's first step: ends the running episode first.
            step: Explicit step (advanced; default: the tracked step, 0 on episode start).
            action_scale: sigma for this step's report (e.g. the policy's standard
                deviation): a scalar or one value per dimension, finite and > 0; None = 1.

        Returns:
            The probe ``clip(a_t + v + K sin(w t dt))``, shape ``(action_dim,)``.
        """
        return self.probe_applied(
            action, episode_start=episode_start, step=step, action_scale=action_scale
        )[0]

    def probe_applied(
        self,
        action: npt.ArrayLike,
        *,
        episode_start: bool = False,
        step: int | None = None,
        action_scale: npt.ArrayLike | None = None,
    ) -> tuple[F64Array, F64Array]:
        """Like :meth:`probe`, and also returns Algorithm 1's action to apply to the env.

        Returns:
            ``(probe, applied)``: the probe, and ``clip(a_t + v(t))``, the shift before this
            step's report; both shape ``(action_dim,)``.
        """
        if step is None:
            step = 0 if episode_start else self._step
        action = np.asarray(action, dtype=np.float64).reshape(-1)
        scale = None if action_scale is None else np.ravel(np.asarray(action_scale, np.float64))
        answer = self._transport.probe(SessionProbe(self.id, step, action, episode_start, scale))
        self._step = step
        return answer

    def report(
        self, q_value: float, *, q_reference: float | None = None, step: int | None = None
    ) -> F64Array:
        """Sends ``Q(s_t, probe)`` and returns the improved action ``clip(a_t + v(t + 1))``.

        Args:
            q_value: The critic's value at the probe.
            q_reference: The critic's value at the applied action ``a_t + v(t)`` in the
                same state: the law then uses ``q_value - q_reference`` (CONTRACT.md 1b).
            step: Explicit step (advanced; default: the pending probe's step).
        """
        step = self._step if step is None else step
        reference = None if q_reference is None else float(q_reference)
        improved = self._transport.report(self.id, step, float(q_value), reference)
        self._step = step + 1
        return improved

    def end_episode(self) -> int:
        """Ends the current episode; returns the number of completed episodes."""
        completed = self._transport.end_episode(self.id)
        self._step = 0
        return completed

    def state(self) -> SessionState:
        """Returns a snapshot of the session (``GetSession``)."""
        return self._transport.get_session(self.id)

    def close(self) -> None:
        """Closes the session on the server; later calls raise ``SessionNotFound``."""
        self._transport.close_session(self.id)

    def __enter__(self) -> Session:
        """Returns self."""
        return self

    def __exit__(self, *exc: object) -> None:
        """Closes the session."""
        self.close()


class SessionBatch:
    """N sessions (one per environment) stepped together: one round trip per probe/report.

    Created by :meth:`EsaClient.create_batch`; arrays have the batch as the first axis, in the
    order of ``ids`` (and ``configs``); ``n`` is N and ``action_dim`` D. It rides out a lost
    server for up to the client's ``reconnect_timeout``, then raises ``ServerUnavailable``
    (the client guide's "Errors, deadlines and restarts").
    """

    def __init__(
        self,
        transport: Transport,
        ids: Sequence[str],
        configs: Sequence[SessionConfig],
        *,
        use_stream: bool = False,
        on_restore: Callable[[int], None] | None = None,
        reconnect: Reconnect | None = None,
    ) -> None:
        """Binds to existing sessions (use :meth:`EsaClient.create_batch`).

        Args:
            transport: What the batch's calls go through.
            ids: The session ids.
            configs: Their configs (one action dimension).
            use_stream: Ask the transport for one persistent stream for the round trips.
            on_restore: Told how many sessions each :meth:`restore` recreated.
            reconnect: How to ride out a lost server; None raises the wire's first error.
        """
        self._transport = transport
        self.ids = tuple(ids)
        self.configs = tuple(configs)
        self.n, self.action_dim = len(self.ids), self.configs[0].action_dim
        self._batch = transport.open_batch(self.ids, self.action_dim, use_stream=use_stream)
        self._on_restore = on_restore
        self.ledger = StepLedger(self.n, self.action_dim)
        """Where the sessions stand, as far as this client knows."""
        self.recovery = Recovery(
            transport, self.ids, self._batch, self.ledger, reconnect, self.restore
        )
        """How the batch's calls ride out a lost server and lost sessions."""
        self._stepper = self._batch.stepper()
        self.sessions_restored = 0
        """How many sessions this batch recreated (by :meth:`restore` or a reconnect)."""

    @property
    def steps(self) -> I64Array:
        """The step each session's next probe (or pending report) carries, shape ``(N,)``."""
        return np.array(self.ledger.steps, dtype=np.int64)

    def probe(
        self,
        actions: npt.ArrayLike,
        episode_starts: npt.ArrayLike | None = None,
        *,
        steps: npt.ArrayLike | None = None,
        action_scales: npt.ArrayLike | None = None,
    ) -> F64Array:
        """Sends the N sampled actions and returns the N probes.

        Args:
            actions: Sampled actions, shape ``(N, D)``.
            episode_starts: Episode-start flags, shape ``(N,)`` (e.g. a VecEnv's ``dones``
                from the previous step); sessions flagged by :meth:`reset` count too.
            steps: Explicit steps (advanced; default: the tracked ones, 0 on episode start).
            action_scales: sigma for this step's reports (e.g. the policy's standard deviation),
                shape ``(N, D)`` or a scalar, finite and > 0; None = 1.
        """
        return self.probe_applied(
            actions, episode_starts, steps=steps, action_scales=action_scales
        )[0]

    def probe_applied(
        self,
        actions: npt.ArrayLike,
        episode_starts: npt.ArrayLike | None = None,
        *,
        steps: npt.ArrayLike | None = None,
        action_scales: npt.ArrayLike | None = None,
    ) -> tuple[F64Array, F64Array]:
        """Like :meth:`probe`, and also returns Algorithm 1's actions to apply to the envs.

        A report deferred with ``report(..., defer=True)`` is sent first, in the same
        round trip on a StepStream. If it fails, its error is raised, nothing of this
        probe is applied and the report stays pending (calling again retries both).

        Returns:
            ``(probes, applied)``, both shape ``(N, D)``: the probes, and
            ``clip(a_t + v(t))``, the shift before this step's report.
        """
        self._stepper.flush(self)
        request = self.ledger.probe_request(actions, episode_starts, steps, action_scales)
        request, answer = self.recovery.probe(request)
        self.ledger.deferred = None
        self.ledger.probed(request)
        return answer

    def step(
        self,
        actions: npt.ArrayLike,
        critic: Critic,
        episode_starts: npt.ArrayLike | None = None,
        *,
        action_scales: npt.ArrayLike | None = None,
        paired: bool = False,
    ) -> tuple[F64Array | None, F64Array]:
        """A whole step of Algorithm 1 (section 1b), in as few waits as the transport allows.

        :meth:`probe_applied`, then the deferred :meth:`report` of ``critic`` at the probes
        (and at the applied actions as ``q_references`` when ``paired``), run as the transport
        decides (the client guide's "Algorithm 1 in one round trip per step"). An error of a
        step sent ahead surfaces at the next call (or :meth:`flush`), nothing of it applied;
        without a reconnect policy a broken exchange starts a new episode in every session at
        the next step.

        Args:
            actions: Sampled actions, shape ``(N, D)``.
            critic: The critic at the N current states, mapping ``(k N, D)`` actions (the
                states tiled k times) to ``(k N,)`` values; or a
                :class:`~esa_client.LinearCritic` or :class:`~esa_client.QuadraticCritic`.
            episode_starts: As for :meth:`probe`.
            action_scales: As for :meth:`probe`.
            paired: Report the critic at the applied actions as the references.

        Returns:
            ``(probes, applied)``, as :meth:`probe_applied` returns them; ``probes`` is None
            for a :class:`~esa_client.LinearCritic` on a StepStream (the server evaluates it
            at probes it answers one step later).

        Raises:
            ValueError: The critic's values are not ``(N,)`` (``(2 N,)`` when ``paired``)
                finite numbers, or a linear or quadratic critic's shapes or values are wrong
                (nothing changed).
        """
        call = StepCall(actions, critic, episode_starts, action_scales, paired)
        return self._stepper.step(self, call)

    def report(
        self,
        q_values: npt.ArrayLike,
        *,
        q_references: npt.ArrayLike | None = None,
        steps: npt.ArrayLike | None = None,
        defer: bool = False,
    ) -> F64Array | None:
        """Sends ``Q(s_t, probe)`` for the N sessions and returns the N improved actions.

        Args:
            q_values: One value per session, shape ``(N,)``.
            q_references: The critic at the applied actions ``a_t + v(t)`` (same states),
                shape ``(N,)``: the law then uses ``q_values - q_references``.
            steps: Explicit steps (advanced; default: the pending probes' steps).
            defer: Send the report with the next :meth:`probe` / :meth:`probe_applied`
                (one round trip on a StepStream) and return None; :meth:`flush`,
                :meth:`end_episode` and :meth:`states` send it first, :meth:`close` drops it.
                If sending fails it stays pending: the next probe retries it, a new ``report``
                replaces it.

        Returns:
            The improved actions ``clip(a_t + v(t + 1))``, shape ``(N, D)``; None if deferred.
        """
        self._stepper.flush(self)
        # Copies: a deferred report must not change with the caller's arrays.
        q = np.array(check_array(q_values, (self.n,), "q_values"))
        references = None
        if q_references is not None:
            references = np.array(check_array(q_references, (self.n,), "q_references"))
        # A report replaces a deferred one (e.g. after it failed), by default at its steps.
        deferred = self.ledger.deferred
        step = self.ledger.steps if deferred is None else deferred.steps
        if steps is not None:
            step = np.asarray(steps, np.int64)
        self.ledger.deferred = None
        request = BatchReport(step, q, references)
        if defer:
            self.ledger.deferred = request
            self.ledger.steps = step + 1
            return None
        sent, improved = self.recovery.report(request)
        self.ledger.steps = sent.steps + 1
        return improved

    def flush(self) -> None:
        """Reads the answer of a step :meth:`step` sent ahead, and sends a deferred report, if any.

        Raises:
            EsaError: The step's error (see :meth:`step`), or the report's (then still pending).
        """
        self._stepper.flush(self)
        if self.ledger.deferred is not None:
            sent, _ = self.recovery.report(self.ledger.deferred)
            self.ledger.deferred = None
            self.ledger.steps = sent.steps + 1

    def restore(self) -> int:
        """Recreates the sessions the server lost, and starts a new episode in every session.

        A recreated session resumes the progress this batch last saw in an answer
        (:class:`SessionProgress`); the running episode's shift and a deferred report are
        gone. Returns how many sessions were recreated.
        """
        self._stepper.reset()
        progress = self._batch.progress()
        restored = restore_sessions(self._transport, self.ids, self.configs, progress)
        self.sessions_restored += restored
        if self._on_restore is not None:
            self._on_restore(restored)
        self.ledger.restarted()
        return restored

    def end_episode(self, indices: npt.ArrayLike | None = None) -> I64Array:
        """Ends the episodes of the given sessions (default: all); returns their episode counts."""
        idx = check_indices(indices, self.n)
        self.flush()
        counts: list[int] = []
        for i in idx.tolist():
            counts.append(self._transport.end_episode(self.ids[i]))
            self.ledger.steps[i] = 0
            self.ledger.starts_due[i] = False
        return np.array(counts, dtype=np.int64)

    def reset(self, indices: npt.ArrayLike | None = None) -> None:
        """Marks the given sessions (default: all) so their next probe starts a new episode."""
        self.ledger.starts_due[check_indices(indices, self.n)] = True

    def states(self) -> list[SessionState]:
        """Returns a snapshot of every session (after sending a deferred report)."""
        self.flush()
        return [self._transport.get_session(i) for i in self.ids]

    def close(self) -> None:
        """Closes the stream (if any) and every session; a deferred report is dropped."""
        self.ledger.deferred = None
        self._stepper.reset()
        self._batch.close()
        for session_id in self.ids:
            self._transport.close_session(session_id)

    def __enter__(self) -> SessionBatch:
        """Returns self."""
        return self

    def __exit__(self, *exc: object) -> None:
        """Closes the batch."""
        self.close()
