"""The esa.v1 contract as a plain Python grpcio server: the baseline esa-server is compared with.

Written the way a Python user would write it: the generated servicer, a dict of
sessions, one small class holding each session's numpy state, and loops over the
sessions of a batch. It implements the update law of CONTRACT.md section 1
(washout filter, shift clamp, learning-rate decay, pass-through, episode starts,
same-step retries) and the step checks; validation is lighter than the real
server's (it is a baseline for speed, not a product).

Usage::

    python bench/python/baseline_server.py [--listen 127.0.0.1:0] [--workers 8]

Prints ``listening on HOST:PORT`` once it accepts calls; stops on SIGINT/SIGTERM.
"""

from __future__ import annotations

import signal
import threading
import uuid
from collections.abc import Iterator
from concurrent import futures
from dataclasses import dataclass

import grpc
import numpy as np
import tyro
from esa_client._proto.esa.v1 import esa_pb2

import esa_pb2_grpc


class BaselineSession:
    """The ESA state of one environment."""

    def __init__(self, config: esa_pb2.SessionConfig) -> None:
        """Sets the session up at rest from its config."""
        d = config.action_dim
        if not 1 <= d <= 4096 or not config.dt > 0:
            raise ValueError(f"expected 1 <= action_dim <= 4096 and dt > 0, got {d}, {config.dt}")

        def vector(values, default: float) -> np.ndarray:
            array = np.asarray(list(values) or [default], dtype=np.float64)
            return np.broadcast_to(array, (d,)).copy()

        self.config = config
        self.dim = d
        self.k = vector(config.amplitude, 0.0)
        self.w = vector(config.frequency, 1.0)
        self.alpha = vector(config.learning_rate, 0.0)
        self.low = vector(config.action_low, -np.inf)
        self.high = vector(config.action_high, np.inf)
        cutoff = config.highpass_cutoff if config.HasField("highpass_cutoff") else self.w.min() / 10
        self.beta = 1.0 / (1.0 + cutoff * config.dt)
        self.limit = config.shift_limit if config.HasField("shift_limit") else np.inf
        self.decay = config.lr_decay if config.HasField("lr_decay") else 1.0
        self.episodes = 0
        self._start_episode()

    def end_episode(self) -> None:
        """Counts the episode as completed and starts the next one."""
        self.episodes += 1
        self._start_episode()

    def _start_episode(self) -> None:
        self.t = 0
        self.v = np.zeros(self.dim)
        self.x_prev = None
        self.y_prev = 0.0
        self.pending = None
        self.last_action = None

    def passthrough(self) -> bool:
        """True once the session has done its ``max_episodes``."""
        return 0 < self.config.max_episodes <= self.episodes

    def probe(self, step: int, action: np.ndarray, episode_start: bool) -> np.ndarray:
        """Stores the sampled action and returns the probe."""
        if episode_start and (self.t > 0 or self.pending is not None):
            self.end_episode()
        if step != self.t:
            raise LookupError(f"expected step {self.t}, got {step}")
        if action.shape != (self.dim,) or not np.all(np.isfinite(action)):
            raise ValueError(f"expected {self.dim} finite action values")
        self.pending = action
        if self.passthrough():
            return np.clip(action, self.low, self.high)
        s = np.sin(self.w * (self.t * self.config.dt))
        return np.clip(action + self.v + self.k * s, self.low, self.high)

    def applied(self) -> np.ndarray:
        """Algorithm 1's action to apply, ``clip(a_t + v(t))``, for the pending probe."""
        shift = 0.0 if self.passthrough() else self.v
        return np.clip(self.pending + shift, self.low, self.high)

    def report(self, step: int, q: float) -> np.ndarray:
        """Updates the shift from the probe's value and returns the improved action."""
        if step == self.t - 1 and self.pending is None and self.last_action is not None:
            return self.last_action
        if step != self.t or self.pending is None:
            raise LookupError(f"expected a report for step {self.t} after a probe, got {step}")
        if not np.isfinite(q):
            raise ValueError("expected a finite q_value")
        if not self.passthrough():
            if self.config.disable_highpass:
                h = q
            else:
                x_prev = q if self.x_prev is None else self.x_prev
                h = self.beta * (self.y_prev + q - x_prev)
                self.x_prev, self.y_prev = q, h
            s = np.sin(self.w * (self.t * self.config.dt))
            alpha = self.alpha * self.decay**self.episodes
            v = np.clip(self.v + alpha * s * h, -self.limit, self.limit)
            if np.all(np.isfinite(v)):
                self.v = v
        action = np.clip(self.pending + self.v, self.low, self.high)
        self.pending = None
        self.last_action = action
        self.t += 1
        return action


class BaselineServicer(esa_pb2_grpc.EsaServiceServicer):
    """EsaService over a dict of :class:`BaselineSession`, one lock for all of them."""

    def __init__(self) -> None:
        """Starts with no sessions."""
        self.sessions: dict[str, BaselineSession] = {}
        self.lock = threading.Lock()

    def _session(self, session_id: str, context: grpc.ServicerContext) -> BaselineSession:
        session = self.sessions.get(session_id)
        if session is None:
            context.abort(grpc.StatusCode.NOT_FOUND, f"session {session_id!r} not found")
        return session

    def _run(self, context: grpc.ServicerContext, work):
        """Runs ``work()`` under the lock, mapping its errors to gRPC codes."""
        try:
            with self.lock:
                return work()
        except ValueError as err:
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, str(err))
        except LookupError as err:
            context.abort(grpc.StatusCode.FAILED_PRECONDITION, str(err))

    def CreateSession(self, request, context):  # noqa: N802 (generated servicer names)
        """Creates (or returns the identical existing) session."""
        session_id = request.session_id or str(uuid.uuid4())

        def create():
            existing = self.sessions.get(session_id)
            if existing is not None:
                if existing.config != request.config:
                    context.abort(grpc.StatusCode.ALREADY_EXISTS, f"{session_id!r} exists")
                return esa_pb2.CreateSessionResponse(session_id=session_id)
            self.sessions[session_id] = BaselineSession(request.config)
            return esa_pb2.CreateSessionResponse(session_id=session_id)

        return self._run(context, create)

    def Probe(self, request, context):  # noqa: N802
        """One session's probe."""

        def probe():
            session = self._session(request.session_id, context)
            action = np.array(request.action, dtype=np.float64)
            out = session.probe(request.step, action, request.episode_start)
            return esa_pb2.ProbeResponse(
                probe=out.tolist(), step=request.step, action=session.applied().tolist()
            )

        return self._run(context, probe)

    def Report(self, request, context):  # noqa: N802
        """One session's report."""

        def report():
            session = self._session(request.session_id, context)
            out = session.report(request.step, request.q_value)
            return esa_pb2.ReportResponse(action=out.tolist(), step=request.step)

        return self._run(context, report)

    def EndEpisode(self, request, context):  # noqa: N802
        """Ends the session's episode."""

        def end():
            session = self._session(request.session_id, context)
            session.end_episode()
            return esa_pb2.EndEpisodeResponse(episodes_completed=session.episodes)

        return self._run(context, end)

    def CloseSession(self, request, context):  # noqa: N802
        """Forgets the session."""
        with self.lock:
            if self.sessions.pop(request.session_id, None) is None:
                context.abort(grpc.StatusCode.NOT_FOUND, f"{request.session_id!r} not found")
        return esa_pb2.CloseSessionResponse()

    def GetSession(self, request, context):  # noqa: N802
        """A snapshot of the session."""
        with self.lock:
            s = self._session(request.session_id, context)
            return esa_pb2.GetSessionResponse(
                config=s.config,
                step=s.t,
                episodes_completed=s.episodes,
                shift=s.v.tolist(),
                probe_pending=s.pending is not None,
            )

    def ProbeBatch(self, request, context):  # noqa: N802
        """Probes every session of the batch (all sessions must exist)."""

        def probe_batch():
            n = len(request.session_ids)
            sessions = [self._session(i, context) for i in request.session_ids]
            actions = np.array(request.actions, dtype=np.float64).reshape(n, -1)
            starts = list(request.episode_starts) or [False] * n
            probes = [
                s.probe(step, a, start)
                for s, step, a, start in zip(sessions, request.steps, actions, starts, strict=True)
            ]
            applied = [s.applied() for s in sessions]
            return esa_pb2.ProbeBatchResponse(
                probes=np.concatenate(probes).tolist(), actions=np.concatenate(applied).tolist()
            )

        return self._run(context, probe_batch)

    def ReportBatch(self, request, context):  # noqa: N802
        """Reports to every session of the batch."""

        def report_batch():
            sessions = [self._session(i, context) for i in request.session_ids]
            actions = [
                s.report(step, q)
                for s, step, q in zip(sessions, request.steps, request.q_values, strict=True)
            ]
            return esa_pb2.ReportBatchResponse(actions=np.concatenate(actions).tolist())

        return self._run(context, report_batch)

    def StepStream(self, request_iterator, context) -> Iterator[esa_pb2.StepStreamResponse]:  # noqa: N802
        """Answers each batch message in order; errors go in-band."""
        for message in request_iterator:
            try:
                if message.HasField("probe_batch"):
                    reply = self.ProbeBatch(message.probe_batch, context)
                    yield esa_pb2.StepStreamResponse(probe_batch=reply)
                else:
                    reply = self.ReportBatch(message.report_batch, context)
                    yield esa_pb2.StepStreamResponse(report_batch=reply)
            except Exception as err:  # noqa: BLE001 (any failure answers this message only)
                error = esa_pb2.StreamError(
                    code=grpc.StatusCode.INTERNAL.value[0], message=str(err)
                )
                yield esa_pb2.StepStreamResponse(error=error)


@dataclass
class Args:
    """A plain Python grpcio server of the esa API, the baseline of the benchmarks."""

    listen: str = "127.0.0.1:0"
    """Loopback host:port (port 0: a free one, printed on start)."""
    workers: int = 8
    """Thread-pool size."""


def main(args: Args) -> None:
    """Serves until SIGINT or SIGTERM."""
    server = grpc.server(futures.ThreadPoolExecutor(max_workers=args.workers))
    esa_pb2_grpc.add_EsaServiceServicer_to_server(BaselineServicer(), server)
    host = args.listen.rpartition(":")[0]
    port = server.add_insecure_port(args.listen)
    server.start()
    print(f"listening on {host}:{port}", flush=True)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    stop.wait()
    server.stop(grace=1.0)


if __name__ == "__main__":
    main(tyro.cli(Args))
