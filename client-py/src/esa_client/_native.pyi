"""esa-core in-process and a gRPC client (the Rust extension built from client-py/native).

An :class:`Engine` holds sessions by id, like an esa-server, and runs the server's all-or-nothing
batches over numpy arrays without a process or a socket in between. Validation and error codes
are the server's (docs/CONTRACT.md section 2): a refused call raises :class:`EngineError` with the
gRPC status code number the server answers the same case with, and changes nothing.
"""

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

INVALID_ARGUMENT: int
"""3: bad config, wrong length, NaN/inf, malformed id, empty or too large batch, repeated id."""
NOT_FOUND: int
"""5: unknown or closed session."""
ALREADY_EXISTS: int
"""6: the id exists with a different config."""
RESOURCE_EXHAUSTED: int
"""8: creating one more session would pass ``max_sessions``."""
FAILED_PRECONDITION: int
"""9: step mismatch, or a report without a pending probe."""
MAX_BATCH_ITEMS: int
"""65,536: most sessions in one batch."""
MAX_BATCH_VALUES: int
"""2^20: most action values (the sessions' dimensions added up) in one batch."""
MAX_ID_BYTES: int
"""128: longest session id, in UTF-8 bytes."""
DETACH_VALUES: int
"""Default ``Engine(detach_values=...)``: larger batches release the GIL while they run."""

def check_config(config: bytes) -> None:
    """Checks an encoded ``esa.v1.SessionConfig`` as creating a session does.

    Every rule of CONTRACT.md sections 1 and 1b.

    Raises:
        ValueError: Naming the first bad field ("frequency[1]: expected ..., got ...").
    """

class EngineError(Exception):
    """A refused call; nothing changed.

    Attributes:
        code: The gRPC status code number (``INVALID_ARGUMENT``, ``NOT_FOUND``, ...).
        message: What to fix, as the server words it (``str(error)`` is the same).
        index: The failing batch item (``item {index}: ...`` in the message), or None.
    """

    code: int
    message: str
    index: int | None

class BatchHandle:
    """Session ids resolved once by :meth:`Engine.resolve`, for batch calls without hashing.

    It names the sessions by id: a session closed after resolving is ``NOT_FOUND`` for its
    item, and one created again under the same id is found again.
    """

    @property
    def ids(self) -> list[str]:
        """The session ids, in item order."""

    def __len__(self) -> int:
        """N, the number of items."""

class Engine:
    """Sessions by id, each stepped by esa-core (the server's law, bit for bit).

    Thread-safe: calls from several Python threads run one at a time; batches of more than
    ``detach_values`` action values release the GIL while they run (their inputs are copied
    first).

    Args:
        max_sessions: Most live sessions (the server's default ``--max-sessions``).
        detach_values: Batches whose sessions' dimensions add up to more than this release the
            GIL.
    """

    def __init__(self, max_sessions: int = 100_000, detach_values: int = ...) -> None: ...
    @property
    def max_sessions(self) -> int:
        """The live-session limit."""

    @property
    def detach_values(self) -> int:
        """Batches of more action values than this release the GIL."""

    def __len__(self) -> int:
        """The number of live sessions."""

    def __contains__(self, session_id: str) -> bool:
        """Whether ``session_id`` names a live session."""

    def create_session(
        self, session_id: str | None, config: bytes, progress: bytes | None = None
    ) -> str:
        """Creates a session (CreateSession) and returns its id.

        Args:
            session_id: 1 to 128 UTF-8 bytes; None or "" generates a UUID.
            config: An encoded ``esa.v1.SessionConfig`` (``SessionConfig.to_proto()
                .SerializeToString()``).
            progress: An encoded ``esa.v1.SessionProgress``: a new session resumes that
                episode count and mean square (CreateSessionRequest.progress); None: none.

        Returns:
            The id. An existing id with an identical config returns that session.

        Raises:
            EngineError: INVALID_ARGUMENT (undecodable or invalid config or progress,
                malformed id), ALREADY_EXISTS (same id, different config),
                RESOURCE_EXHAUSTED (limit).
        """

    def get_session(self, session_id: str) -> bytes:
        """An encoded ``esa.v1.GetSessionResponse`` snapshot of the session.

        Raises:
            EngineError: INVALID_ARGUMENT (malformed id), NOT_FOUND.
        """

    def close_session(self, session_id: str) -> None:
        """Closes the session; its id is NOT_FOUND afterwards.

        Raises:
            EngineError: INVALID_ARGUMENT (malformed id), NOT_FOUND.
        """

    def end_episode(self, session_id: str) -> int:
        """Ends the session's episode (EndEpisode); returns its completed episodes.

        Raises:
            EngineError: INVALID_ARGUMENT (malformed id), NOT_FOUND.
        """

    def probe_one(
        self,
        session_id: str,
        step: int,
        action: npt.ArrayLike,
        episode_start: bool = False,
        action_scale: npt.ArrayLike | None = None,
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """Probe of one session (the server's unary Probe).

        Returns:
            ``(probe, applied)``, float64[D] each.

        Raises:
            EngineError: As Probe: INVALID_ARGUMENT, NOT_FOUND, FAILED_PRECONDITION (no index).
            OverflowError: ``step`` is negative or above 2^64 - 1.
        """

    def report_one(
        self, session_id: str, step: int, q_value: float, q_reference: float | None = None
    ) -> npt.NDArray[np.float64]:
        """Report of one session (the server's unary Report): returns the improved action.

        Raises:
            EngineError: As Report: INVALID_ARGUMENT, NOT_FOUND, FAILED_PRECONDITION (no index).
            OverflowError: ``step`` is negative or above 2^64 - 1.
        """

    def resolve(self, session_ids: Sequence[str]) -> BatchHandle:
        """Resolves session ids (item order) into a handle for :meth:`probe` and :meth:`report`.

        Raises:
            EngineError: INVALID_ARGUMENT (no ids, more than MAX_BATCH_ITEMS, a malformed id,
                an id twice), NOT_FOUND (an unknown id); errors of one id name its item.
        """

    def probe(
        self,
        handle: BatchHandle,
        steps: npt.ArrayLike,
        actions: npt.ArrayLike,
        episode_starts: npt.ArrayLike | None = None,
        action_scales: npt.ArrayLike | None = None,
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """ProbeBatch: probes every session of the handle at once; all-or-nothing.

        Arrays are read in C order whatever their shape; uint64, float64 and bool C-contiguous
        arrays are read without a copy, anything else is converted by numpy.

        Args:
            handle: The N sessions.
            steps: uint64[N], each session's current step (0 with an episode start).
            actions: float64[N, D] (or the N actions concatenated), the sampled actions.
            episode_starts: bool[N], or None for all False.
            action_scales: float64[N, D] like ``actions`` (each > 0), or None for all 1.

        Returns:
            ``(probes, applied)``: the probes and Algorithm 1's applied actions
            ``clip(a_t + v(t))``, float64[N, D] (flat when the sessions' D differ).

        Raises:
            EngineError: As ProbeBatch: INVALID_ARGUMENT, FAILED_PRECONDITION, NOT_FOUND (a
                session closed since resolving); ``index`` names the failing item.
            ValueError: ``steps`` holds negative integers, or an array cannot be converted.
            TypeError: ``steps`` is not integers.
        """

    def report(
        self,
        handle: BatchHandle,
        steps: npt.ArrayLike,
        q_values: npt.ArrayLike,
        q_references: npt.ArrayLike | None = None,
    ) -> npt.NDArray[np.float64]:
        """ReportBatch: reports Q to every session of the handle at once; all-or-nothing.

        Args:
            handle: The N sessions.
            steps: uint64[N], the steps probed (or the step just applied: a replay).
            q_values: float64[N], Q at each probe.
            q_references: float64[N], Q at each applied action, or None.

        Returns:
            The improved actions ``clip(a_t + v(t + 1))``, float64[N, D] (flat when the
            sessions' D differ).

        Raises:
            EngineError: As ReportBatch: INVALID_ARGUMENT, FAILED_PRECONDITION, NOT_FOUND;
                ``index`` names the failing item.
        """

    def step_closed_form(
        self,
        handle: BatchHandle,
        steps: npt.NDArray[np.int64],
        actions: npt.ArrayLike,
        episode_starts: npt.ArrayLike,
        action_scales: npt.ArrayLike | None,
        gain: npt.ArrayLike,
        offset: npt.ArrayLike,
        paired: bool,
        curvature: npt.ArrayLike | None = None,
        low: npt.ArrayLike | None = None,
        high: npt.ArrayLike | None = None,
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """ProbeBatch, then ReportBatch of a closed-form critic, in one call.

        Without ``curvature`` the critic is linear, ``Q_i(a) = gain_i . a + offset_i``
        (``esa_client.LinearCritic``); with it, concave quadratic in the clipped action,
        ``Q_i(a) = offset_i + sum_j (gain_ij x_j + curvature_ij x_j^2)`` with
        ``x = clip(a, low, high)`` (``esa_client.QuadraticCritic``). The report sends the
        critic at each probe (and, when ``paired``, at each applied action as
        ``q_reference``) with the probe's step. All-or-nothing: the critic is checked before
        the probe.

        Args:
            handle: The N sessions.
            steps: int64[N], C-contiguous: the tracked steps (an episode start steps at 0),
                advanced in place (each to its step + 1) when the step is applied.
            actions: As for :meth:`probe`.
            episode_starts: As for :meth:`probe`.
            action_scales: As for :meth:`probe`.
            gain: float64, the sessions' dimensions concatenated (``(N, D)``), finite.
            offset: float64[N], finite.
            paired: Report the critic at the applied actions as the references.
            curvature: float64 as ``gain``, finite and ``<= 0``; None for a linear critic.
            low: With ``curvature``, the box's float64[D] lower bounds (``-inf`` where open;
                or one per action value), or None with ``high`` for no box.
            high: Its upper bounds, as ``low``; ``low <= high``.

        Returns:
            ``(probes, applied)``, as :meth:`probe` returns them.

        Raises:
            EngineError: As ProbeBatch; INVALID_ARGUMENT for a gain, offset or curvature of
                the wrong length or with a non-finite value, a positive curvature, or bounds
                of the wrong length, NaN or with a low above its high.
            ValueError: ``low`` or ``high`` without a ``curvature``, or ``steps`` holding a
                negative integer or not C-contiguous.
            TypeError: ``steps`` is not a one-dimensional int64 array.
        """

class QuadraticHead:
    """ESAPPO's quadratic head at a step's states: forward pass and closed form in one call.

    :class:`esa_client.common.quadratic_head.QuadraticHead`'s forward pass in float32, its
    closed form in float64.

    Args:
        layers: The ``(weight, bias)`` of its three linear layers, input first, each weight
            ``(outputs, inputs)``.

    Raises:
        ValueError: If there are not 3 layers, their shapes do not chain, or the last one's
            outputs are not ``2 D``.
    """

    def __init__(
        self, layers: Sequence[tuple[npt.NDArray[np.floating], npt.NDArray[np.floating]]]
    ) -> None: ...
    def closed_form(
        self,
        features: npt.NDArray[np.floating],
        mean: npt.NDArray[np.floating],
        std: npt.NDArray[np.floating],
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """``(gain, curvature, offset)`` (``(N, D)``, ``(N, D)``, ``(N,)``) at N states.

        Args:
            features: The states' features, ``(N, F)``.
            mean: The policy's mean, ``(N, D)``, in any units.
            std: The policy's std, ``(N, D)``, in ``mean``'s units.

        Raises:
            ValueError: If a shape disagrees with the head, a value is not finite, or a std
                is not positive.
        """

class StepStats:
    """The sums behind a learner's per-step ESA statistics (``esa/...`` in its log).

    Per step, over its N envs: ``mean_abs_shift`` (mean ``|applied - sampled|``),
    ``clipped_fraction`` (envs with an applied action outside the clip bounds), with a std
    ``shift_over_std`` (mean ``|z|``, ``z = (applied - sampled) / std``) and ``kl_per_dim``
    (mean ``z^2 / 2``), and the sampled ``improvement``; :meth:`means` averages each over its
    steps. Counts (``sessions_restored``, ...) are totals.

    Args:
        clip_low: The bounds the env clips the actions to, D values, in the actions' units.
        clip_high: See ``clip_low``.

    Raises:
        ValueError: If the bounds are empty or of different lengths.
    """

    def __init__(self, clip_low: Sequence[float], clip_high: Sequence[float]) -> None: ...
    def add_step(
        self,
        sampled: npt.NDArray[np.floating],
        applied: npt.NDArray[np.floating],
        scales: npt.NDArray[np.floating] | None = None,
    ) -> None:
        """Adds one step: sampled and applied actions ``(N, D)``, the std ``(N, D)`` or None.

        Raises:
            ValueError: If a shape is not ``(N, D)`` with one N (nothing is added).
            TypeError: If an argument is not a numpy array.
        """

    def add_improvement(self, value: float) -> None:
        """Adds one step's critic improvement, ``Q(applied) - Q(sampled)`` averaged over envs."""

    def add_count(self, key: str, count: float) -> None:
        """Adds ``count`` to the total ``key``."""

    def means(self) -> dict[str, float]:
        """Each statistic's mean over its steps, and the counts, added since the last reset."""

    def reset(self) -> None:
        """Forgets everything added."""

class StatusError(Exception):
    """A failed call of :class:`GrpcClient`: the server's status, or the connection's.

    Attributes:
        code: The gRPC status code number (UNAVAILABLE = 14 for a server that cannot be
            reached or a closed client, DEADLINE_EXCEEDED = 4 for no answer in time).
        message: The status message.
        index: The failing batch item, from the status details (``esa.v1.BatchItem``), or None.
    """

    code: int
    message: str
    index: int | None

class GrpcBatch:
    """The batch calls of N sessions (unary, or on a StepStream), from :meth:`GrpcClient.batch`.

    Arrays are read as :meth:`Engine.probe` reads them; answers are float64[N, D].
    """

    def probe(
        self,
        steps: npt.ArrayLike,
        actions: npt.ArrayLike,
        episode_starts: npt.ArrayLike,
        action_scales: npt.ArrayLike | None = None,
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """ProbeBatch: returns ``(probes, applied)``.

        Raises:
            StatusError: The server's error (``index`` names the failing item), or the wire's.
            ValueError: ``steps`` holds negative integers, an array cannot be converted, or
                the answer is not N * D values.
        """

    def report(
        self,
        steps: npt.ArrayLike,
        q_values: npt.ArrayLike,
        q_references: npt.ArrayLike | None = None,
    ) -> npt.NDArray[np.float64]:
        """ReportBatch: returns the improved actions.

        Raises:
            StatusError: As :meth:`probe`.
            ValueError: As :meth:`probe`.
        """

    def report_then_probe(
        self,
        report_steps: npt.ArrayLike,
        q_values: npt.ArrayLike,
        q_references: npt.ArrayLike | None,
        steps: npt.ArrayLike,
        actions: npt.ArrayLike,
        episode_starts: npt.ArrayLike,
        action_scales: npt.ArrayLike | None = None,
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """ReportBatch, then the next step's ProbeBatch; returns the probe's ``(probes, applied)``.

        On a batch with a stream both are sent before either answer is read: one round trip.

        Raises:
            StatusError: The report's error if it failed (the probe then changed nothing
                unless it started every session's episode), else the probe's; or the wire's.
            ValueError: As :meth:`probe`.
        """

    def send_step_linear(
        self,
        steps: npt.ArrayLike,
        actions: npt.ArrayLike,
        episode_starts: npt.ArrayLike,
        action_scales: npt.ArrayLike | None,
        gains: npt.ArrayLike,
        offsets: npt.ArrayLike,
        paired: bool,
    ) -> None:
        """Sends a ``step_linear_batch`` (probe, linear critic, report) and returns at once.

        The request is on the wire when this returns; its answer is read by
        :meth:`receive_step`. Only a batch with a stream can send one.

        Raises:
            StatusError: The wire's error (the stream could not be opened or written).
            ValueError: The batch has no stream, or an array cannot be converted.
        """

    def send_step(
        self,
        steps: npt.ArrayLike,
        actions: npt.ArrayLike,
        episode_starts: npt.ArrayLike,
        action_scales: npt.ArrayLike | None,
        q_values: npt.ArrayLike,
        q_references: npt.ArrayLike | None,
    ) -> None:
        """Sends a ``step_batch`` (probe, the critic's values, report) and returns at once.

        The values are the critic at the probes computed ahead (:meth:`StepAhead.probes`)
        and, as references, at the applied actions. Answered like :meth:`send_step_linear`.

        Raises:
            StatusError: The wire's error (the stream could not be opened or written).
            ValueError: The batch has no stream, or an array cannot be converted.
        """

    def receive_step(
        self,
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """The answer to the oldest unanswered :meth:`send_step_linear` or :meth:`send_step`.

        Returns:
            ``(probes, applied, shifts)``, each float64[N, D]: the shifts are ``v(t + 1)``.

        Raises:
            StatusError: That request's error (nothing of it was applied), or the wire's
                (UNAVAILABLE when the stream broke: whether it was applied is unknown).
        """

    def resend_step(self) -> None:
        """Sends the last step sent ahead again, on a new stream; returns at once.

        For a step whose answer the wire lost and that the server did not apply; read its
        answer with :meth:`receive_step`.

        Raises:
            StatusError: FAILED_PRECONDITION when no step sent ahead waits for its answer.
        """

    def progress(
        self,
    ) -> tuple[npt.NDArray[np.uint64], npt.NDArray[np.float64]] | None:
        """Each session's progress in the last answer that carried it (a probe's or a step's).

        Returns:
            ``(episodes_completed, response_mean_squares)``: uint64[N], and float64[N] with -1
            where m is unset (empty when no session normalizes); None before such an answer.
        """

    def close(self) -> None:
        """Ends the batch's ``StepStream``, if one is open; the sessions stay. Idempotent."""

    def __len__(self) -> int:
        """N, the number of sessions."""

class StepAhead:
    """Algorithm 1's applied actions and probes from shifts known ahead, with esa-core's code.

    For a client of the pipelined step: ``clip(a + clamp(v, -bound, bound), lo, hi)`` with
    ``bound = min(L, kappa * sigma)``, per session and dimension, and the probe
    ``clip(a + clamp(v, -bound, bound) + K sin(w t dt), lo, hi)``: the bits the server's
    probe gives for the shift ``v`` (CONTRACT.md section 1b, implementation note 8).

    Args:
        configs: One encoded ``esa.v1.SessionConfig`` per session, all of one action
            dimension.

    Raises:
        EngineError: A config is not valid (INVALID_ARGUMENT).
        ValueError: No config, or configs of different action dimensions.
    """

    def __init__(self, configs: list[bytes]) -> None: ...
    def probes(
        self,
        shifts: npt.ArrayLike,
        steps: npt.ArrayLike,
        actions: npt.ArrayLike,
        action_scales: npt.ArrayLike | None = None,
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """``(probes, applied)``, each float64[N, D], of step ``steps[i]`` (shape (N,)).

        ``shifts``, ``actions`` and ``action_scales`` (None: 1) are of shape (N, D).

        Raises:
            EngineError: A length does not match, an action is not finite or a scale not
                finite and > 0 (INVALID_ARGUMENT, ``index`` names the session).
            ValueError: ``steps`` not non-negative integers.
        """

    def probes_quadratic(
        self,
        shifts: npt.ArrayLike,
        steps: npt.ArrayLike,
        actions: npt.ArrayLike,
        action_scales: npt.ArrayLike | None,
        critic: tuple[
            npt.ArrayLike, npt.ArrayLike, npt.ArrayLike, npt.ArrayLike | None, npt.ArrayLike | None
        ],
        paired: bool,
    ) -> tuple[
        npt.NDArray[np.float64],
        npt.NDArray[np.float64],
        npt.NDArray[np.float64],
        npt.NDArray[np.float64] | None,
    ]:
        """:meth:`probes`, and a quadratic critic's values there: ``(probes, applied, q, refs)``.

        ``critic`` is a ``QuadraticCritic`` (``(gain, curvature, offset, low, high)``), checked
        and evaluated as the in-process engine does (esa-core's code, the same bits); ``q`` is
        its values at the probes, float64[N], ``refs`` at the applied actions when ``paired``,
        else None.

        Raises:
            EngineError: As :meth:`probes`, or a bad critic (INVALID_ARGUMENT).
            ValueError: ``steps`` not non-negative integers.
        """

    def __len__(self) -> int:
        """N, the number of sessions."""

class GrpcClient:
    """A gRPC client of one esa-server (tonic), the GIL released while a call waits.

    It connects on the first call, and again after a lost connection. Every call has the
    deadline ``timeout`` and carries ``authorization: Bearer <token>`` when a token is given.

    Args:
        address: ``host:port`` (TCP) or ``unix:/path/to/socket``.
        timeout: Deadline of every call, in seconds.
        token: The server's auth token, or None.
        tls: Connect over TLS (rustls), to a ``host:port`` address.
        ca: PEM of the CA(s) that issued the server's certificate; None trusts the Mozilla
            roots. TLS only.
        cert: PEM of this client's certificate chain (mutual TLS), with ``key``. TLS only.
        key: PEM of the certificate's private key. TLS only.
        domain: The name to check the server's certificate against instead of the
            address's host. TLS only.

    Raises:
        ValueError: A malformed address, timeout, token or TLS setting.
    """

    def __init__(
        self,
        address: str,
        timeout: float,
        token: str | None = None,
        *,
        tls: bool = False,
        ca: bytes | None = None,
        cert: bytes | None = None,
        key: bytes | None = None,
        domain: str | None = None,
    ) -> None: ...
    def create_session(self, session_id: str, config: bytes, progress: bytes | None = None) -> str:
        """CreateSession with an encoded ``esa.v1.SessionConfig``; returns the id.

        ``progress``, an encoded ``esa.v1.SessionProgress``, resumes a lost session's.
        """

    def get_session(self, session_id: str) -> bytes:
        """GetSession: the encoded ``esa.v1.GetSessionResponse``."""

    def close_session(self, session_id: str) -> None:
        """CloseSession."""

    def end_episode(self, session_id: str) -> int:
        """EndEpisode: returns the completed episodes."""

    def probe_one(
        self,
        session_id: str,
        step: int,
        action: npt.ArrayLike,
        episode_start: bool,
        action_scale: npt.ArrayLike | None = None,
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """Probe: returns ``(probe, applied)``, float64[D] each.

        Raises:
            StatusError: The server's error, or the wire's.
            OverflowError: ``step`` is negative or above 2^64 - 1.
        """

    def report_one(
        self, session_id: str, step: int, q_value: float, q_reference: float | None = None
    ) -> npt.NDArray[np.float64]:
        """Report: returns the improved action, float64[D].

        Raises:
            StatusError: The server's error, or the wire's.
            OverflowError: ``step`` is negative or above 2^64 - 1.
        """

    def batch(self, session_ids: Sequence[str], dim: int, use_stream: bool = False) -> GrpcBatch:
        """The batch calls of these sessions (in item order), all of action dimension ``dim``.

        With ``use_stream`` every call is a message of a ``StepStream`` of the batch's own
        (opened by its first call, and again after a failure of the wire), and
        :meth:`GrpcBatch.report_then_probe` takes one round trip; else they are unary calls.
        """

    def healthy(self, timeout: float, wait_for_ready: bool = False) -> bool:
        """Whether the server's health service answers SERVING within ``timeout`` seconds.

        ``wait_for_ready`` retries while the server cannot be reached, up to the deadline.
        """

    def close(self) -> None:
        """Drops the connection; later calls raise StatusError(UNAVAILABLE). Idempotent."""
