"""The per-session calls, which ``Engine`` and ``GrpcClient`` of ``_native`` take alike."""

from __future__ import annotations

from .._native import Engine, GrpcClient
from .._proto.esa.v1 import esa_pb2
from ..errors import TypedErrors
from ..state import F64Array, SessionState
from .messages import SessionProbe


class NativeSessionCalls:
    """The per-session Transport methods over ``sessions``, an ``Engine`` or a ``GrpcClient``."""

    def __init__(self, sessions: Engine | GrpcClient, typed_errors: TypedErrors) -> None:
        """Forwards to ``sessions``."""
        self._sessions = sessions
        self._typed_errors = typed_errors

    def create_session(self, session_id: str, config: esa_pb2.SessionConfig) -> str:
        """``CreateSession``; an empty id gets a UUID."""
        with self._typed_errors:
            return self._sessions.create_session(session_id, config.SerializeToString())

    def resume_session(
        self, session_id: str, config: esa_pb2.SessionConfig, progress: esa_pb2.SessionProgress
    ) -> str:
        """``CreateSession`` of a lost session, resuming its ``progress``."""
        encoded = progress.SerializeToString()
        with self._typed_errors:
            return self._sessions.create_session(session_id, config.SerializeToString(), encoded)

    def get_session(self, session_id: str) -> SessionState:
        """``GetSession``."""
        with self._typed_errors:
            encoded = self._sessions.get_session(session_id)
        return SessionState.from_proto(esa_pb2.GetSessionResponse.FromString(encoded))

    def close_session(self, session_id: str) -> None:
        """``CloseSession``."""
        with self._typed_errors:
            self._sessions.close_session(session_id)

    def end_episode(self, session_id: str) -> int:
        """``EndEpisode``; returns the completed-episode count."""
        with self._typed_errors:
            return self._sessions.end_episode(session_id)

    def probe(self, request: SessionProbe) -> tuple[F64Array, F64Array]:
        """``Probe`` of one session; returns the probe and the applied action."""
        with self._typed_errors:
            return self._sessions.probe_one(*request)

    def report(
        self, session_id: str, step: int, q_value: float, q_reference: float | None
    ) -> F64Array:
        """``Report`` of one session; returns the improved action."""
        with self._typed_errors:
            return self._sessions.report_one(session_id, step, q_value, q_reference)
