"""The transport interface: what :class:`~esa_client.Session` and ``SessionBatch`` call.

The client is split the way httpx splits its ``Client`` from its transports: sessions and
batches are written once against :class:`Transport` and :class:`BatchTransport`, and each
way of reaching the update law implements them:

- the in-process engine of ``esa_client._native``, which takes numpy arrays directly
  (:mod:`esa_client.transports.in_process`);
- gRPC through the Rust client of ``esa_client._native`` (:mod:`esa_client.transports.grpc`);
- Zenoh queries to one server or N shards (:mod:`esa_client.transports.zenoh`).

:class:`~esa_client.EsaClient`'s constructors choose a transport and own its lifetime. The
batch half (:class:`BatchTransport`) is array-based, not protobuf-based, so that an
in-process implementation builds no messages; transports that send messages build them.
What a wire offers beyond the batch's round trips (a whole step in one engine call, or a
step sent ahead of its answer) a batch says through :meth:`BatchTransport.fused` and
:meth:`BatchTransport.ahead`, so that sessions never ask which transport they are on.
Every failure a transport raises is an :class:`~esa_client.errors.EsaError` (built by
:func:`~esa_client.errors.error_for`), with ``index`` set when one batch item caused it.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from typing import NamedTuple, Protocol

import numpy as np

from .._proto.esa.v1 import esa_pb2
from ..state import BoolArray, F64Array, I64Array, SessionProgress, SessionState

SMALLEST_SCALE = float(np.finfo(np.float32).tiny)
"""The floor of the action scale sent for a policy's std (the contract needs sigma > 0)."""


class BatchProbe(NamedTuple):
    """The probes of one step for the N sessions of a batch (``ProbeBatch``).

    Attributes:
        steps: Each session's step, shape ``(N,)``.
        actions: The sampled actions, shape ``(N, D)``.
        episode_starts: Episode-start flags, shape ``(N,)``.
        action_scales: sigma per session and dimension, shape ``(N, D)``; None for all 1.
    """

    steps: I64Array
    actions: F64Array
    episode_starts: BoolArray
    action_scales: F64Array | None


class BatchReport(NamedTuple):
    """The reports of one step for the N sessions of a batch (``ReportBatch``).

    Attributes:
        steps: Each session's step (the probed one), shape ``(N,)``.
        q_values: Q at each probe, shape ``(N,)``.
        q_references: Q at each applied action, shape ``(N,)``; None for no reference.
    """

    steps: I64Array
    q_values: F64Array
    q_references: F64Array | None


class LinearCritic(NamedTuple):
    """A critic linear in the action at each session's state: ``Q_i(a) = gain_i . a + offset_i``.

    A linear advantage head has this form; an in-process engine evaluates it itself
    (:meth:`~esa_client.session.SessionBatch.step`).

    Attributes:
        gain: ``gain_i`` per session and dimension, shape ``(N, D)``.
        offset: ``offset_i`` per session, shape ``(N,)``.
    """

    gain: F64Array
    offset: F64Array

    def __call__(self, actions: F64Array) -> F64Array:
        """Q of ``(k N, D)`` actions for the N states tiled k times, shape ``(k N,)``."""
        points = actions.reshape(-1, *self.gain.shape)
        values: F64Array = ((points * self.gain).sum(axis=2) + self.offset).reshape(-1)
        return values


class AheadBatch(Protocol):
    """A batch that sends a whole step and reads its answer later.

    The wire's ``step_linear_batch`` and ``step_batch`` (CONTRACT.md section 1b,
    implementation note 8): the server probes, evaluates the linear critic (or takes the
    critic's values the client computed at the same probes) and reports in one request, and
    answers with the shifts ``v(t + 1)``, from which the client computes the next step's
    applied actions and probes itself. Requests are answered in the order they were sent.
    """

    def send_step_linear(self, request: BatchProbe, critic: LinearCritic, paired: bool) -> None:
        """Sends the step for a linear critic; returns once it is on its way."""
        ...

    def send_step(
        self, request: BatchProbe, q_values: F64Array, q_references: F64Array | None
    ) -> None:
        """Sends the step with the critic's values at its probes; returns once it is on its way."""
        ...

    def receive_step(self) -> tuple[F64Array, F64Array, F64Array]:
        """The oldest unanswered step's ``(probes, applied, shifts)``, each ``(N, D)``.

        Raises the step's error (nothing of it was applied), or the wire's (whether it
        was applied is then unknown).
        """
        ...

    def resend_step(self) -> None:
        """Sends the step whose answer the wire lost again; ``receive_step`` reads its answer."""
        ...


class QuadraticCritic(NamedTuple):
    """A critic concave quadratic in the action at each session's state, flat past a box.

    ``Q_i(a) = offset_i + sum_j (gain_ij x_j + curvature_ij x_j^2)`` with
    ``x = clip(a, low, high)``, the action the environment executes, and every
    ``curvature_ij <= 0``. ESAPPO's quadratic head has this form; an in-process engine
    evaluates it itself (:meth:`~esa_client.session.SessionBatch.step`), any other transport
    here at the probes.

    Attributes:
        gain: ``gain_i`` per session and dimension, shape ``(N, D)``.
        curvature: ``curvature_i`` per session and dimension, ``<= 0``, shape ``(N, D)``.
        offset: ``offset_i`` per session, shape ``(N,)``.
        low: The box's lower bounds in the actions' units, shape ``(D,)`` (``-inf`` where
            open); None with ``high`` None for no box.
        high: Its upper bounds, shape ``(D,)`` (``+inf`` where open), or None.
    """

    gain: F64Array
    curvature: F64Array
    offset: F64Array
    low: F64Array | None = None
    high: F64Array | None = None

    def __call__(self, actions: F64Array) -> F64Array:
        """Q of ``(k N, D)`` actions for the N states tiled k times, shape ``(k N,)``."""
        points = actions.reshape(-1, *self.gain.shape)
        if self.low is not None and self.high is not None:
            points = np.clip(points, self.low, self.high)
        terms = self.gain * points + self.curvature * points * points
        values: F64Array = (terms.sum(axis=2) + self.offset).reshape(-1)
        return values


class FusedBatch(Protocol):
    """A batch whose engine runs a whole step in one call: the in-process engine's."""

    def step_closed_form(
        self, request: BatchProbe, critic: LinearCritic | QuadraticCritic, paired: bool
    ) -> tuple[F64Array, F64Array]:
        """ProbeBatch, then ReportBatch of ``critic`` at the probes, in one engine call.

        A quadratic critic is evaluated at the clipped probes. With ``paired``, the critic at
        the applied actions is reported as the references. Returns the probes and the applied
        actions.
        """
        ...


class BatchTransport(ABC):
    """The round trips of one batch of N sessions (all of one action dimension D).

    Every call is all-or-nothing: on an error no session changed, and the error's
    ``index`` names the failing item (its position in the batch) when one item caused it.
    Subclasses implement :meth:`probe` and :meth:`report`; the pair of :meth:`report_then_probe`
    goes in turn here (two round trips, and a failed report raises before the probe is
    sent, so the probe changed nothing), for wires that have nothing to pipeline.
    """

    @abstractmethod
    def probe(self, request: BatchProbe) -> tuple[F64Array, F64Array]:
        """``ProbeBatch``: returns the probes and the applied actions, each ``(N, D)``."""

    @abstractmethod
    def report(self, request: BatchReport) -> F64Array:
        """``ReportBatch``: returns the improved actions, ``(N, D)``."""

    def report_then_probe(
        self, report: BatchReport, probe: BatchProbe
    ) -> tuple[F64Array, F64Array]:
        """The report of step t, then the probe of the next step.

        Returns the probe's answer (the report's improved actions are not needed: its
        caller applies the probe's actions). If the report fails, its error is raised and
        the probe changed nothing.
        """
        self.report(report)
        return self.probe(probe)

    def fused(self) -> FusedBatch | None:
        """This batch's whole-step engine calls (:class:`FusedBatch`), if it has any.

        The in-process engine runs a step (probe, a linear or quadratic critic, report) in one call;
        over a wire there is none, and the step is its round trips.
        """
        return None

    def ahead(self) -> AheadBatch | None:
        """This batch's calls that send a whole step before reading its answer, if any.

        Only a wire that carries steps in order without waiting (gRPC's ``StepStream``)
        has them.
        """
        return None

    def progress(self) -> list[SessionProgress] | None:
        """Each session's progress in the last answer read, where the wire carries it.

        None before an answer carried it, and for an in-process engine, which never loses a
        session to recreate.
        """
        return None

    def close(self) -> None:  # noqa: B027 (a default, not abstract: most hold nothing)
        """Releases what the batch holds (e.g. its stream); the sessions stay."""


class PipelinedBatch(BatchTransport):
    """A :class:`BatchTransport` whose wire carries the report and the next probe at once.

    The pair is sent in one go (one round trip), except when the probe starts a new
    episode for every session: that probe would succeed even after its report failed,
    leaving the report unrecoverable, so that pair goes in turn and a failed report stops
    the probe (once per episode end, not per step). Subclasses implement
    :meth:`_pipelined`.
    """

    @abstractmethod
    def _pipelined(self, report: BatchReport, probe: BatchProbe) -> tuple[F64Array, F64Array]:
        """Sends both before reading either answer; raises the report's error first."""

    def report_then_probe(
        self, report: BatchReport, probe: BatchProbe
    ) -> tuple[F64Array, F64Array]:
        """The report and the probe in one round trip (in turn at an all-sessions start)."""
        if probe.episode_starts.all():
            return super().report_then_probe(report, probe)
        return self._pipelined(report, probe)


class Transport(Protocol):
    """One way of reaching esa sessions: the calls of ``esa.v1.EsaService``.

    Session ids are 1 to 128 bytes of UTF-8. Every call has the transport's deadline and
    raises :class:`~esa_client.errors.EsaError` subclasses only.
    """

    def create_session(self, session_id: str, config: esa_pb2.SessionConfig) -> str:
        """Creates a session (an empty id: one is generated) and returns its id."""
        ...

    def resume_session(
        self, session_id: str, config: esa_pb2.SessionConfig, progress: esa_pb2.SessionProgress
    ) -> str:
        """Creates a session that resumes a lost one's ``progress``; returns its id."""
        ...

    def get_session(self, session_id: str) -> SessionState:
        """Returns a snapshot of the session."""
        ...

    def close_session(self, session_id: str) -> None:
        """Closes the session; its id is unknown afterwards."""
        ...

    def end_episode(self, session_id: str) -> int:
        """Ends the session's episode; returns its completed-episode count."""
        ...

    def probe(
        self,
        session_id: str,
        step: int,
        action: F64Array,
        episode_start: bool,
        action_scale: F64Array | None,
    ) -> tuple[F64Array, F64Array]:
        """``Probe`` of one session: returns the probe and the applied action, ``(D,)`` each."""
        ...

    def report(
        self, session_id: str, step: int, q_value: float, q_reference: float | None
    ) -> F64Array:
        """``Report`` of one session: returns the improved action, ``(D,)``."""
        ...

    def open_batch(
        self, ids: Sequence[str], action_dim: int, *, use_stream: bool
    ) -> BatchTransport:
        """The round trips of a batch of these (existing) sessions.

        Args:
            ids: The N session ids, in batch order.
            action_dim: D, shared by the N sessions.
            use_stream: Prefer one persistent stream (gRPC ``StepStream``) where the
                transport has one; others ignore it or use their message equivalent.
        """
        ...

    def healthy(self, timeout: float, *, wait_for_ready: bool = False) -> bool:
        """True if every server behind this transport answers within ``timeout`` seconds."""
        ...

    def close(self) -> None:
        """Releases the transport (connections, threads). Idempotent."""
        ...
