"""Sessions on an esa server: one :class:`Session`, or a :class:`SessionBatch` for N envs.

Both track their sessions' step counters, so callers only pass actions and
Q-values. A failed call changes no counter, so repeating it is safe (the server
treats a repeated probe or report of the same step as a retry). One exception
follows from the contract: if an episode-start probe reached the server but its
answer was lost, repeating it ends one more (empty) episode, which counts toward
``lr_decay`` and ``max_episodes``.

Algorithm 1's step (CONTRACT.md section 1b) needs one round trip: ``probe_applied``
returns the probe and the action to apply, ``clip(a_t + v(t))``; the report of that
step can then be deferred (``report(..., defer=True)``) and rides with the next
probe, pipelined on a StepStream.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ._proto.esa.v1 import esa_pb2
from .config import SessionConfig
from .transport import call

if TYPE_CHECKING:
    from .client import EsaClient


@dataclass(frozen=True)
class SessionState:
    """A snapshot of one session (``GetSession``).

    Attributes:
        config: The config as given at creation.
        step: Current step t inside the episode.
        episodes_completed: Number of completed episodes e.
        shift: Current shift v, shape ``(action_dim,)``.
        probe_pending: True between a probe and its report.
        response_mean_square: The running mean square m of the filtered response
            (``normalize_response``); None until the first non-zero response seeds it.
    """

    config: SessionConfig
    step: int
    episodes_completed: int
    shift: np.ndarray
    probe_pending: bool
    response_mean_square: float | None = None

    @classmethod
    def from_proto(cls, message: esa_pb2.GetSessionResponse) -> SessionState:
        """Builds the snapshot from a ``GetSessionResponse``."""
        return cls(
            config=SessionConfig.from_proto(message.config),
            step=message.step,
            episodes_completed=message.episodes_completed,
            shift=np.array(message.shift, dtype=np.float64),
            probe_pending=message.probe_pending,
            response_mean_square=(
                message.response_mean_square if message.HasField("response_mean_square") else None
            ),
        )


def as_batch_configs(
    configs: SessionConfig | Sequence[SessionConfig], n: int | None
) -> tuple[SessionConfig, ...]:
    """Returns one config per session, checking they share one action dimension.

    Args:
        configs: One config for all sessions, or one per session.
        n: Number of sessions; required with a single config, else must match.
    """
    if isinstance(configs, SessionConfig):
        if n is None or n < 1:
            raise ValueError(f"expected n >= 1 sessions for a single config, got {n}")
        return (configs,) * n
    out = tuple(configs)
    if not out or (n is not None and n != len(out)):
        raise ValueError(f"expected {n if n is not None else '>= 1'} configs, got {len(out)}")
    dims = {c.action_dim for c in out}
    if len(dims) != 1:
        raise ValueError(f"expected one action_dim across the batch, got {sorted(dims)}")
    return out


def check_array(
    values: np.ndarray | Sequence[float] | Sequence[bool],
    shape: tuple[int, ...],
    name: str,
    *,
    dtype: type = np.float64,
    finite: bool = False,
    error: Callable[[str], Exception] = ValueError,
) -> np.ndarray:
    """Returns ``values`` as a ``dtype`` array, checking its shape (and finiteness).

    Args:
        values: A batch argument, e.g. the actions.
        shape: The shape it must have.
        name: The argument's name, for the message.
        dtype: The array's dtype.
        finite: Also require every value to be finite.
        error: Builds the exception from the message (``ValueError`` by default).

    Raises:
        Exception: Built by ``error``, if the shape is wrong or a value is not finite.
    """
    out = np.asarray(values, dtype=dtype)
    if out.shape != shape:
        raise error(f"expected {name} of shape {shape}, got {out.shape}")
    if finite and not np.all(np.isfinite(out)):
        raise error(f"expected finite {name}, got {out!r}")
    return out


def check_indices(indices: Sequence[int] | np.ndarray | None, n: int) -> np.ndarray:
    """Returns ``indices`` (default: all N) as an int array, checking the range."""
    if indices is None:
        return np.arange(n)
    idx = np.asarray(indices, dtype=np.int64).reshape(-1)
    if idx.size and (idx.min() < 0 or idx.max() >= n):
        raise ValueError(f"expected indices in [0, {n}), got {idx.tolist()}")
    return idx


class Session:
    """One ESA session on the server; created by :meth:`EsaClient.create_session`.

    Attributes:
        id: The session id.
        config: The session config.
    """

    def __init__(self, client: EsaClient, session_id: str, config: SessionConfig, step: int = 0):
        """Binds to an existing server session (use the client's factory methods)."""
        self._client = client
        self.id = session_id
        self.config = config
        self._step = step

    @property
    def step(self) -> int:
        """The step t the next probe (or pending report) carries."""
        return self._step

    def probe(
        self,
        action: np.ndarray | Sequence[float],
        *,
        episode_start: bool = False,
        step: int | None = None,
        action_scale: float | Sequence[float] | np.ndarray | None = None,
    ) -> np.ndarray:
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
        action: np.ndarray | Sequence[float],
        *,
        episode_start: bool = False,
        step: int | None = None,
        action_scale: float | Sequence[float] | np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Like :meth:`probe`, and also returns Algorithm 1's action to apply to the env.

        Returns:
            ``(probe, applied)``: the probe, and ``clip(a_t + v(t))``, the shift before this
            step's report; both shape ``(action_dim,)``.
        """
        if step is None:
            step = 0 if episode_start else self._step
        request = esa_pb2.ProbeRequest(
            session_id=self.id,
            step=step,
            action=np.asarray(action, dtype=np.float64).reshape(-1).tolist(),
            episode_start=episode_start,
            action_scale=[] if action_scale is None else np.ravel(action_scale).tolist(),
        )
        response = call(self._client.stub.Probe, request, self._client.timeout)
        self._step = step
        return (
            np.array(response.probe, dtype=np.float64),
            np.array(response.action, dtype=np.float64),
        )

    def report(
        self, q_value: float, *, q_reference: float | None = None, step: int | None = None
    ) -> np.ndarray:
        """Sends ``Q(s_t, probe)`` and returns the improved action ``clip(a_t + v(t + 1))``.

        Args:
            q_value: The critic's value at the probe.
            q_reference: The critic's value at the applied action ``a_t + v(t)`` in the
                same state: the law then uses ``q_value - q_reference`` (CONTRACT.md 1b).
            step: Explicit step (advanced; default: the pending probe's step).

        Returns:
            The improved action, shape ``(action_dim,)``.
        """
        step = self._step if step is None else step
        request = esa_pb2.ReportRequest(session_id=self.id, step=step, q_value=float(q_value))
        if q_reference is not None:
            request.q_reference = float(q_reference)
        response = call(self._client.stub.Report, request, self._client.timeout)
        self._step = step + 1
        return np.array(response.action, dtype=np.float64)

    def end_episode(self) -> int:
        """Ends the current episode; returns the number of completed episodes."""
        request = esa_pb2.EndEpisodeRequest(session_id=self.id)
        response = call(self._client.stub.EndEpisode, request, self._client.timeout)
        self._step = 0
        return response.episodes_completed

    def state(self) -> SessionState:
        """Returns a snapshot of the session (``GetSession``)."""
        return self._client.session_state(self.id)

    def close(self) -> None:
        """Closes the session on the server; later calls raise ``SessionNotFound``."""
        request = esa_pb2.CloseSessionRequest(session_id=self.id)
        call(self._client.stub.CloseSession, request, self._client.timeout)

    def __enter__(self) -> Session:
        """Returns self."""
        return self

    def __exit__(self, *exc: object) -> None:
        """Closes the session."""
        self.close()


class SessionBatch:
    """N sessions (one per environment) stepped together: one round trip per probe/report.

    Created by :meth:`EsaClient.create_batch`. Arrays in and out are numpy with the
    batch as the first axis.

    Attributes:
        ids: The N session ids, in batch order.
        configs: The N session configs.
        n: Number of sessions.
        action_dim: Shared action dimension D.
    """

    def __init__(
        self,
        client: EsaClient,
        ids: Sequence[str],
        configs: Sequence[SessionConfig],
        *,
        use_stream: bool = False,
    ) -> None:
        """Binds to existing server sessions (use :meth:`EsaClient.create_batch`)."""
        self._client = client
        self.ids = tuple(ids)
        self.configs = tuple(configs)
        self.n, self.action_dim = len(self.ids), self.configs[0].action_dim
        self._transport = client.batch_transport(self.ids, self.action_dim, use_stream=use_stream)
        self._steps = np.zeros(self.n, dtype=np.int64)
        self._next_starts = np.zeros(self.n, dtype=bool)
        # A report sent with the next probe (``report(..., defer=True)``).
        self._deferred: esa_pb2.ReportBatchRequest | None = None

    @property
    def steps(self) -> np.ndarray:
        """The step each session's next probe (or pending report) carries, shape ``(N,)``."""
        return self._steps.copy()

    def probe(
        self,
        actions: np.ndarray,
        episode_starts: np.ndarray | Sequence[bool] | None = None,
        *,
        steps: np.ndarray | Sequence[int] | None = None,
        action_scales: np.ndarray | float | None = None,
    ) -> np.ndarray:
        """Sends the N sampled actions and returns the N probes.

        Args:
            actions: Sampled actions, shape ``(N, D)``.
            episode_starts: Episode-start flags, shape ``(N,)`` (e.g. a VecEnv's ``dones``
                from the previous step); sessions flagged by :meth:`reset` count too.
            steps: Explicit steps (advanced; default: the tracked ones, 0 on episode start).
            action_scales: sigma per session and dimension for this step's reports (e.g. the
                policy's standard deviation), shape ``(N, D)`` or a scalar, finite and > 0;
                None = 1.

        Returns:
            The probes, shape ``(N, D)``.
        """
        return self.probe_applied(
            actions, episode_starts, steps=steps, action_scales=action_scales
        )[0]

    def probe_applied(
        self,
        actions: np.ndarray,
        episode_starts: np.ndarray | Sequence[bool] | None = None,
        *,
        steps: np.ndarray | Sequence[int] | None = None,
        action_scales: np.ndarray | float | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Like :meth:`probe`, and also returns Algorithm 1's actions to apply to the envs.

        A report deferred with ``report(..., defer=True)`` is sent first, in the same
        round trip on a StepStream. If it fails, its error is raised, nothing of this
        probe is applied and the report stays pending (calling again retries both).

        Returns:
            ``(probes, applied)``, both shape ``(N, D)``: the probes, and
            ``clip(a_t + v(t))``, the shift before this step's report.
        """
        a = check_array(actions, (self.n, self.action_dim), "actions")
        starts = self._next_starts.copy()
        if episode_starts is not None:
            starts |= check_array(episode_starts, (self.n,), "episode_starts", dtype=bool)
        step = np.where(starts, 0, self._steps) if steps is None else np.asarray(steps, np.int64)
        scales: list[float] = []
        if action_scales is not None:
            shape = (self.n, self.action_dim)
            scales = np.broadcast_to(np.asarray(action_scales, np.float64), shape).ravel().tolist()
        request = esa_pb2.ProbeBatchRequest(
            session_ids=self.ids,
            steps=step.tolist(),
            actions=a.ravel().tolist(),
            episode_starts=starts.tolist(),
            action_scales=scales,
        )
        if self._deferred is None:
            response = self._transport.probe_batch(request)
        else:
            _, response = self._transport.report_then_probe(self._deferred, request)
            self._deferred = None
        self._steps = step
        self._next_starts[:] = False
        shape = (self.n, self.action_dim)
        return (
            np.array(response.probes, dtype=np.float64).reshape(shape),
            np.array(response.actions, dtype=np.float64).reshape(shape),
        )

    def report(
        self,
        q_values: np.ndarray | Sequence[float],
        *,
        q_references: np.ndarray | Sequence[float] | None = None,
        steps: np.ndarray | Sequence[int] | None = None,
        defer: bool = False,
    ) -> np.ndarray | None:
        """Sends ``Q(s_t, probe)`` for the N sessions and returns the N improved actions.

        Args:
            q_values: One value per session, shape ``(N,)``.
            q_references: The critic at the applied actions ``a_t + v(t)`` (same states),
                shape ``(N,)``: the law then uses ``q_values - q_references``.
            steps: Explicit steps (advanced; default: the pending probes' steps).
            defer: Send the report with the next :meth:`probe` / :meth:`probe_applied`
                (one round trip for both on a StepStream) and return None. For trainers
                that apply :meth:`probe_applied`'s actions and do not need this answer.
                :meth:`flush` sends it on its own; :meth:`end_episode`, :meth:`states`
                and :meth:`close` flush first. If sending it fails, it stays pending:
                calling the probe again retries both (after a lost connection), and a
                new ``report`` replaces it (after a bad value).

        Returns:
            The improved actions ``clip(a_t + v(t + 1))``, shape ``(N, D)``; None if deferred.
        """
        q = check_array(q_values, (self.n,), "q_values")
        references: list[float] = []
        if q_references is not None:
            references = check_array(q_references, (self.n,), "q_references").tolist()
        if steps is not None:
            step = np.asarray(steps, np.int64)
        elif self._deferred is not None:
            # A report of the same steps replaces the deferred one (e.g. after it failed).
            step = np.asarray(self._deferred.steps, np.int64)
        else:
            step = self._steps
        self._deferred = None
        request = esa_pb2.ReportBatchRequest(
            session_ids=self.ids,
            steps=step.tolist(),
            q_values=q.tolist(),
            q_references=references,
        )
        if defer:
            self._deferred = request
            self._steps = step + 1
            return None
        response = self._transport.report_batch(request)
        self._steps = step + 1
        return np.array(response.actions, dtype=np.float64).reshape(self.n, self.action_dim)

    def flush(self) -> None:
        """Sends a deferred report now (nothing if none is pending).

        Raises:
            EsaError: The report's error; it then stays pending.
        """
        if self._deferred is not None:
            self._transport.report_batch(self._deferred)
            self._deferred = None

    def restore(self) -> int:
        """Recreates the sessions the server lost, and starts a new episode in every session.

        For a :class:`SessionNotFound` after a server restart or a TTL expiry (see
        :meth:`EsaClient.restore_sessions`: the shift of the running episode, the episode
        count and the response's mean square of a lost session are gone). A deferred
        report is dropped; the next probe starts step 0 everywhere.

        Returns:
            How many sessions were recreated.
        """
        self._deferred = None
        restored = self._client.restore_sessions(self.ids, self.configs)
        self._steps[:] = 0
        self._next_starts[:] = True
        return restored

    def end_episode(self, indices: Sequence[int] | np.ndarray | None = None) -> np.ndarray:
        """Ends the episodes of the given sessions now (one call each; default: all).

        Returns:
            The completed-episode counts of those sessions.
        """
        idx = check_indices(indices, self.n)
        self.flush()
        counts = []
        for i in idx.tolist():
            request = esa_pb2.EndEpisodeRequest(session_id=self.ids[i])
            counts.append(call(self._client.stub.EndEpisode, request, self._client.timeout))
            self._steps[i] = 0
            self._next_starts[i] = False
        return np.array([c.episodes_completed for c in counts], dtype=np.int64)

    def reset(self, indices: Sequence[int] | np.ndarray | None = None) -> None:
        """Marks the given sessions (default: all) so their next probe starts a new episode.

        This costs no round trip: the flag rides on the next :meth:`probe`.
        """
        self._next_starts[check_indices(indices, self.n)] = True

    def states(self) -> list[SessionState]:
        """Returns a snapshot of every session (after sending a deferred report)."""
        self.flush()
        return [self._client.session_state(i) for i in self.ids]

    def close(self) -> None:
        """Closes the stream (if any) and every session on the server.

        A deferred report is dropped: it cannot change anything the caller still sees.
        """
        self._deferred = None
        self._transport.close()
        for session_id in self.ids:
            request = esa_pb2.CloseSessionRequest(session_id=session_id)
            call(self._client.stub.CloseSession, request, self._client.timeout)

    def __enter__(self) -> SessionBatch:
        """Returns self."""
        return self

    def __exit__(self, *exc: object) -> None:
        """Closes the batch."""
        self.close()
