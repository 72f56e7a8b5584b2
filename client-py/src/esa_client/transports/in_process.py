"""The Transport over ``esa_client._native.Engine``: esa-core in this process."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

from .._native import BatchHandle, Engine, EngineError
from ..errors import TypedErrors
from ..state import BoolArray, F64Array, I64Array
from .base import BatchTransport
from .messages import BatchProbe, BatchReport, LinearCritic, QuadraticCritic
from .native_calls import NativeSessionCalls
from .stepping import CLOSED_FORM, StepCall, Stepper, check_critic

if TYPE_CHECKING:
    from ..session import SessionBatch

_typed_errors = TypedErrors(EngineError)


class InProcessBatch(BatchTransport):
    """A batch's round trips as ``Engine.probe`` / ``Engine.report`` calls.

    Ids resolve at the first call, which a missing session fails as on a server.
    """

    def __init__(self, engine: Engine, ids: Sequence[str]) -> None:
        """Steps the sessions ``ids`` of ``engine``, in this order."""
        self._engine = engine
        self._ids = list(ids)
        self._handle: BatchHandle | None = None

    def _resolved(self) -> BatchHandle:
        if self._handle is None:
            self._handle = self._engine.resolve(self._ids)
        return self._handle

    def probe(self, request: BatchProbe) -> tuple[F64Array, F64Array]:
        """ProbeBatch in-process."""
        with _typed_errors:
            return self._engine.probe(self._resolved(), *request)

    def stepper(self) -> FusedStepper:
        """The engine runs a whole step in one call."""
        return FusedStepper(self)

    def step_closed_form(
        self,
        steps: I64Array,
        inputs: tuple[F64Array, BoolArray, F64Array | None],
        critic: LinearCritic | QuadraticCritic,
        paired: bool,
    ) -> tuple[F64Array, F64Array]:
        """ProbeBatch, then ReportBatch of ``critic``, in one call; ``steps`` advance in place."""
        curved: tuple[F64Array | None, F64Array | None, F64Array | None] = (None, None, None)
        if isinstance(critic, QuadraticCritic):
            curved = (critic.curvature, critic.low, critic.high)
        with _typed_errors:
            return self._engine.step_closed_form(
                self._resolved(), steps, *inputs, critic.gain, critic.offset, paired, *curved
            )

    def report(self, request: BatchReport) -> F64Array:
        """ReportBatch in-process."""
        with _typed_errors:
            return self._engine.report(self._resolved(), *request)


class FusedStepper(Stepper):
    """A step in one engine call for a linear or quadratic critic; round trips for others."""

    def __init__(self, fused: InProcessBatch) -> None:
        """Steps through ``fused``'s engine calls."""
        self._fused = fused

    def step(self, batch: SessionBatch, call: StepCall) -> tuple[F64Array | None, F64Array]:
        """One engine call (see :meth:`~esa_client.SessionBatch.step`)."""
        critic = call.critic
        if not isinstance(critic, CLOSED_FORM):
            return super().step(batch, call)
        batch.flush()
        # No wire to ride out here, and the engine advances the steps itself.
        ledger = batch.ledger
        inputs = ledger.probe_inputs(call.actions, call.episode_starts, call.action_scales)
        try:
            answer = self._fused.step_closed_form(ledger.steps, inputs, critic, call.paired)
        except ValueError:
            # esa-core checks the critic itself (checking first would cost more than the
            # step); a refusal is then told in the words of every transport.
            check_critic(critic, batch.n, batch.action_dim)
            raise
        ledger.starts_due.fill(False)
        return answer


class InProcessTransport(NativeSessionCalls):
    """The Transport over ``engine``, or a new one with ``max_sessions`` (None = 100,000)."""

    def __init__(self, engine: Engine | None = None, *, max_sessions: int | None = None) -> None:
        """Uses ``engine``, or a new one."""
        if engine is not None and max_sessions is not None:
            raise ValueError("expected engine or max_sessions, got both")
        if engine is None:
            engine = Engine() if max_sessions is None else Engine(max_sessions=max_sessions)
        self.engine = engine
        super().__init__(engine, _typed_errors)

    def open_batch(
        self, ids: Sequence[str], action_dim: int, *, use_stream: bool
    ) -> InProcessBatch:
        """An :class:`InProcessBatch` (a call is already one round trip: no stream)."""
        return InProcessBatch(self.engine, ids)

    def healthy(self, timeout: float, *, wait_for_ready: bool = False) -> bool:
        """Always True: the engine is in this process."""
        return True

    def close(self) -> None:
        """Nothing to release: the engine goes with its last reference."""

    def __repr__(self) -> str:
        """Names the transport (the engine has no address)."""
        return "InProcessTransport()"
