"""The transport interface that ``Session`` and ``SessionBatch`` call.

The batch half takes arrays, not messages, so that the in-process engine builds none.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from typing import Protocol

import numpy as np

from .._proto.esa.v1 import esa_pb2
from ..state import F64Array, SessionProgress, SessionState
from .messages import BatchProbe, BatchReport, LinearCritic, QuadraticCritic, SessionProbe
from .stepping import Stepper

__all__ = [
    "SMALLEST_SCALE",
    "BatchProbe",
    "BatchReport",
    "BatchTransport",
    "LinearCritic",
    "PipelinedBatch",
    "QuadraticCritic",
    "SessionProbe",
    "Transport",
]

SMALLEST_SCALE = float(np.finfo(np.float32).tiny)
"""The floor of the action scale sent for a policy's std (the contract needs sigma > 0)."""


class BatchTransport(ABC):
    """The all-or-nothing round trips of one batch of N sessions of action dimension D."""

    @abstractmethod
    def probe(self, request: BatchProbe) -> tuple[F64Array, F64Array]:
        """``ProbeBatch``: returns the probes and the applied actions, each ``(N, D)``."""

    @abstractmethod
    def report(self, request: BatchReport) -> F64Array:
        """``ReportBatch``: returns the improved actions, ``(N, D)``."""

    def report_then_probe(
        self, report: BatchReport, probe: BatchProbe
    ) -> tuple[F64Array, F64Array]:
        """The report of step t, then (if it succeeded) the next probe; returns its answer."""
        self.report(report)
        return self.probe(probe)

    def stepper(self) -> Stepper:
        """How :meth:`~esa_client.SessionBatch.step` runs on this batch: its round trips."""
        return Stepper()

    def progress(self) -> list[SessionProgress] | None:
        """Each session's progress in the last answer that carried it; None before (or never)."""
        return None

    def close(self) -> None:  # noqa: B027 (a default, not abstract: most hold nothing)
        """Releases what the batch holds (e.g. its stream); the sessions stay."""


class PipelinedBatch(BatchTransport):
    """A :class:`BatchTransport` whose wire carries the report and the next probe at once.

    Except when every session starts an episode: that probe would succeed after its report
    failed, leaving the report unrecoverable, so that pair goes in turn.
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
    """The calls of ``esa.v1.EsaService``, each with the transport's deadline, raising EsaError."""

    def create_session(self, session_id: str, config: esa_pb2.SessionConfig) -> str:
        """Creates a session (an empty id: one is generated) and returns its id."""

    def resume_session(
        self, session_id: str, config: esa_pb2.SessionConfig, progress: esa_pb2.SessionProgress
    ) -> str:
        """Creates a session that resumes a lost one's ``progress``; returns its id."""

    def get_session(self, session_id: str) -> SessionState:
        """Returns a snapshot of the session."""

    def close_session(self, session_id: str) -> None:
        """Closes the session; its id is unknown afterwards."""

    def end_episode(self, session_id: str) -> int:
        """Ends the session's episode; returns its completed-episode count."""

    def probe(self, request: SessionProbe) -> tuple[F64Array, F64Array]:
        """``Probe`` of one session: returns the probe and the applied action, ``(D,)`` each."""

    def report(
        self, session_id: str, step: int, q_value: float, q_reference: float | None
    ) -> F64Array:
        """``Report`` of one session: returns the improved action, ``(D,)``."""

    def open_batch(
        self, ids: Sequence[str], action_dim: int, *, use_stream: bool
    ) -> BatchTransport:
        """The round trips of these existing sessions (``use_stream``: on one stream if any)."""

    def healthy(self, timeout: float, *, wait_for_ready: bool = False) -> bool:
        """True if every server behind this transport answers within ``timeout`` seconds."""

    def close(self) -> None:
        """Releases the transport (connections, threads). Idempotent."""
