"""The ESA update law in numpy (CONTRACT.md sections 1 and 1b): the tests' reference.

An executable specification, written independently of esa-core, that the server, the
in-process engine and every transport are cross-checked against. It lives with the
tests, not in the package: trainers and benchmarks use the in-process engine
(``EsaClient.in_process()``). :class:`ReferenceBatch` and :class:`ReferenceSession` have
the API of :class:`esa_client.SessionBatch` and :class:`esa_client.Session` and raise the
same typed errors, so either can be swapped in; :class:`ReferenceClient` mirrors a client.

Test modules import it as ``reference_law`` (``conftest.py`` loads it; pytest's
``--import-mode=importlib`` keeps this folder off ``sys.path``).
"""

from __future__ import annotations

import uuid
from collections.abc import Sequence

import numpy as np

from esa_client.config import SessionConfig
from esa_client.errors import InvalidArgument, SessionNotFound, StatusCode, StepMismatch
from esa_client.state import SessionState, as_batch_configs, check_array, check_indices


def _invalid(message: str) -> InvalidArgument:
    # The server's status code, so that callers handle both alike.
    return InvalidArgument(message, StatusCode.INVALID_ARGUMENT)


class ReferenceBatch:
    """N independent ESA sessions with the same action dimension, updated in lockstep.

    Args:
        configs: One config per session (all with the same ``action_dim``).
        ids: Session ids; None = random UUIDs.
    """

    def __init__(self, configs: Sequence[SessionConfig], ids: Sequence[str] | None = None) -> None:
        """Creates the sessions at rest."""
        self.configs = tuple(configs)
        self.ids = tuple(ids) if ids is not None else tuple(str(uuid.uuid4()) for _ in configs)
        n, d = len(self.configs), self.configs[0].action_dim
        self.n, self.action_dim = n, d

        def stack(name: str) -> np.ndarray:
            return np.stack([c.vector(name) for c in self.configs])

        self._k = stack("amplitude")
        self._w = stack("frequency")
        self._alpha = stack("learning_rate")
        # Unbounded sides saturate at the largest double, as on the server, so that an
        # overflowing a + v still clips to a finite action.
        big = np.finfo(np.float64).max
        self._low = np.clip(stack("action_low"), -big, big)
        self._high = np.clip(stack("action_high"), -big, big)
        dt = np.array([c.dt for c in self.configs])
        cutoff = np.array(
            [
                c.highpass_cutoff
                if c.highpass_cutoff is not None
                else min(c.vector("frequency")) / 10
                for c in self.configs
            ]
        )
        self._dt = dt[:, None]
        self._beta = 1.0 / (1.0 + cutoff * dt)
        self._filtered = np.array([not c.disable_highpass for c in self.configs])
        self._limit = np.array(
            [c.shift_limit if c.shift_limit is not None else np.inf for c in self.configs]
        )[:, None]
        self._decay = np.array(
            [c.lr_decay if c.lr_decay is not None else 1.0 for c in self.configs]
        )
        self._max_episodes = np.array([c.max_episodes for c in self.configs], dtype=np.int64)
        # Section 1b.
        self._normalize = np.array([c.normalize_response for c in self.configs])
        self._rho = np.array(
            [c.response_rms_rate if c.response_rms_rate is not None else 0.05 for c in self.configs]
        )
        self._clip = np.array(
            [c.response_clip if c.response_clip is not None else 3.0 for c in self.configs]
        )
        self._keep = np.array(
            [1.0 - c.shift_leak if c.shift_leak is not None else 1.0 for c in self.configs]
        )[:, None]
        self._trust = np.array(
            [c.trust_region if c.trust_region is not None else np.inf for c in self.configs]
        )[:, None]

        self._t = np.zeros(n, dtype=np.int64)
        self._episodes = np.zeros(n, dtype=np.int64)
        self._v = np.zeros((n, d))
        self._x_prev = np.zeros(n)
        self._y_prev = np.zeros(n)
        self._filter_at_rest = np.ones(n, dtype=bool)
        self._pending = np.zeros(n, dtype=bool)
        self._action = np.zeros((n, d))
        self._retryable = np.zeros(n, dtype=bool)
        self._last_action = np.zeros((n, d))
        self._next_starts = np.zeros(n, dtype=bool)
        self._scale = np.ones((n, d))
        # m per session, valid where seeded (both persist across episodes).
        self._mean_square = np.zeros(n)
        self._seeded = np.zeros(n, dtype=bool)
        self._closed = False

    @property
    def steps(self) -> np.ndarray:
        """The current step t of every session, shape ``(N,)``."""
        steps: np.ndarray = self._t.copy()
        return steps

    def _check_open(self) -> None:
        if self._closed:
            raise SessionNotFound("sessions of this batch were closed", StatusCode.NOT_FOUND)

    def _steps_arg(
        self, steps: np.ndarray | Sequence[int] | None, default: np.ndarray
    ) -> np.ndarray:
        if steps is None:
            return default
        out = np.asarray(steps)
        if out.shape != (self.n,) or not np.issubdtype(out.dtype, np.integer) or np.any(out < 0):
            raise _invalid(f"expected steps of shape ({self.n},) with integers >= 0, got {out!r}")
        return out.astype(np.int64)

    def _end(self, mask: np.ndarray) -> None:
        self._episodes += mask
        self._t[mask] = 0
        self._v[mask] = 0.0
        self._filter_at_rest |= mask
        self._pending &= ~mask
        self._retryable &= ~mask

    def _passthrough(self) -> np.ndarray:
        return (self._max_episodes > 0) & (self._episodes >= self._max_episodes)

    def _phase(self) -> np.ndarray:
        phase: np.ndarray = np.sin(self._w * (self._t[:, None] * self._dt))
        return phase

    def probe(
        self,
        actions: np.ndarray,
        episode_starts: np.ndarray | Sequence[bool] | None = None,
        *,
        steps: np.ndarray | Sequence[int] | None = None,
        action_scales: np.ndarray | float | None = None,
    ) -> np.ndarray:
        """Returns the probes ``clip(a + v + K sin(w t dt))``, shape ``(N, D)``.

        Args:
            actions: The sampled actions, shape ``(N, D)``.
            episode_starts: Per-session episode-start flags, shape ``(N,)``; also set by
                :meth:`reset`. A flagged session with ``t > 0`` or a pending probe first
                ends its episode.
            steps: Explicit step per session (advanced; default: the tracked step).
            action_scales: sigma for this step's reports, ``(N, D)`` or a scalar; None = 1.

        Raises:
            InvalidArgument: Wrong shape or non-finite action or scale (nothing changes).
            StepMismatch: An explicit step is not the session's step (nothing changes).
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
        """Returns ``(probes, applied)``: the probes and ``clip(a + v(t))`` (Algorithm 1)."""
        self._check_open()
        a = check_array(actions, (self.n, self.action_dim), "actions", finite=True, error=_invalid)
        scale = np.ones((self.n, self.action_dim))
        if action_scales is not None:
            scale = np.broadcast_to(np.asarray(action_scales, np.float64), scale.shape).copy()
            if not np.all(np.isfinite(scale) & (scale > 0)):
                raise _invalid(f"expected action_scales finite and > 0, got {scale!r}")
        starts = self._next_starts.copy()
        if episode_starts is not None:
            starts |= check_array(
                episode_starts, (self.n,), "episode_starts", dtype=bool, error=_invalid
            )
        ends = starts & ((self._t > 0) | self._pending)
        expected = np.where(ends, 0, self._t)
        given = self._steps_arg(steps, expected)
        wrong = np.flatnonzero(given != expected)
        if wrong.size:
            i = int(wrong[0])
            raise StepMismatch(
                f"item {i}: expected step {expected[i]}, got {given[i]}",
                StatusCode.FAILED_PRECONDITION,
            )
        self._end(ends)
        self._next_starts[:] = False
        passthrough = self._passthrough()[:, None]
        self._scale = np.where(passthrough, self._scale, scale)
        # This probe's sigma bounds v at once, so a_t + v(t) keeps this step's trust region.
        bound = np.minimum(self._limit, self._trust * self._scale)
        self._v = np.where(passthrough, self._v, np.clip(self._v, -bound, bound))
        perturbed = np.where(passthrough, a, a + (self._v + self._k * self._phase()))
        applied = np.where(passthrough, a, a + self._v)
        self._action = a
        self._pending[:] = True
        self._retryable[:] = False
        return (
            np.clip(perturbed, self._low, self._high),
            np.clip(applied, self._low, self._high),
        )

    def report(
        self,
        q_values: np.ndarray | Sequence[float],
        *,
        q_references: np.ndarray | Sequence[float] | None = None,
        steps: np.ndarray | Sequence[int] | None = None,
        defer: bool = False,
    ) -> np.ndarray | None:
        """Takes ``Q(s_t, probe)`` per session and returns the improved actions, shape ``(N, D)``.

        A report carrying step ``t - 1`` right after that step was reported returns the
        same improved action again without updating anything (a safe retry). With
        ``q_references`` the response is ``q - q_reference``. ``defer`` is accepted for
        signature compatibility with :meth:`esa_client.SessionBatch.report`: the report
        is applied at once (there is no round trip to save) and None returned.

        Raises:
            InvalidArgument: Wrong shape or non-finite value (nothing changes).
            StepMismatch: No pending probe, or an explicit step that does not match.
        """
        self._check_open()
        q = check_array(q_values, (self.n,), "q_values", finite=True, error=_invalid)
        if q_references is not None:
            reference = check_array(
                q_references, (self.n,), "q_references", finite=True, error=_invalid
            )
        given = self._steps_arg(steps, self._t)
        fresh = self._pending & (given == self._t)
        retry = ~self._pending & self._retryable & (given == self._t - 1)
        wrong = np.flatnonzero(~(fresh | retry))
        if wrong.size:
            i = int(wrong[0])
            reason = "no pending probe" if not self._pending[i] else f"expected step {self._t[i]}"
            raise StepMismatch(
                f"item {i}: {reason}, got step {given[i]}", StatusCode.FAILED_PRECONDITION
            )
        with np.errstate(invalid="ignore", over="ignore"):
            x = q if q_references is None else q - reference
            # Filter at rest on the first report of an episode: x_{-1} = x_0, y_{-1} = 0.
            x_prev = np.where(self._filter_at_rest, x, self._x_prev)
            y_prev = np.where(self._filter_at_rest, 0.0, self._y_prev)
            h = np.where(self._filtered, self._beta * (y_prev + x - x_prev), x)
            v_new, m_new, has_m, normalized_ok = self._step_candidates(h)
        active = fresh & ~self._passthrough()
        update = active & np.all(np.isfinite(v_new), axis=1) & normalized_ok
        bound = np.minimum(self._limit, self._trust * self._scale)
        # A skipped update keeps v, inside this report's bound (as the server does).
        kept = np.clip(self._v, -bound, bound)
        self._v = np.where(update[:, None], v_new, np.where(active[:, None], kept, self._v))
        committed = update & self._normalize & has_m
        self._mean_square = np.where(committed, m_new, self._mean_square)
        self._seeded |= committed
        self._x_prev = np.where(fresh, x, self._x_prev)
        # An overflowed output restarts the filter from this sample instead of poisoning
        # the rest of the episode with inf/NaN (same as the server).
        self._y_prev = np.where(fresh, np.where(np.isfinite(h), h, 0.0), self._y_prev)
        self._filter_at_rest &= ~fresh
        improved = np.clip(self._action + self._v, self._low, self._high)
        self._last_action = np.where(fresh[:, None], improved, self._last_action)
        self._t += fresh
        self._pending &= ~fresh
        self._retryable |= fresh
        return None if defer else self._last_action.copy()

    def _step_candidates(
        self, h: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The candidate v and m, where m is set, and where the normalization stayed finite."""
        alpha = self._alpha * (self._decay**self._episodes)[:, None]
        # The first non-zero h seeds m (NaN counts as non-zero, as on the server).
        has_m = self._seeded | (h != 0.0)
        m_new = np.where(
            self._seeded, (1.0 - self._rho) * self._mean_square + self._rho * (h * h), h * h
        )
        g = np.where(has_m, np.clip(h / np.sqrt(m_new + 1e-12), -self._clip, self._clip), 0.0)
        normalized_ok = ~self._normalize | ((~has_m | np.isfinite(m_new)) & np.isfinite(g))
        response = np.where(self._normalize, g, h)[:, None]
        gain = np.where(self._normalize[:, None], alpha * self._scale, alpha)
        bound = np.minimum(self._limit, self._trust * self._scale)
        v_new = np.clip(self._keep * self._v + gain * self._phase() * response, -bound, bound)
        return v_new, m_new, has_m, normalized_ok

    def flush(self) -> None:
        """Nothing is ever deferred here; present for API symmetry with SessionBatch."""

    def end_episode(self, indices: Sequence[int] | np.ndarray | None = None) -> np.ndarray:
        """Ends the episodes of the given sessions (default: all); returns their episode counts."""
        self._check_open()
        idx = check_indices(indices, self.n)
        mask = np.zeros(self.n, dtype=bool)
        mask[idx] = True
        self._end(mask)
        self._next_starts &= ~mask
        counts: np.ndarray = self._episodes[idx].copy()
        return counts

    def reset(self, indices: Sequence[int] | np.ndarray | None = None) -> None:
        """Marks the given sessions (default: all) so their next probe starts a new episode."""
        self._check_open()
        self._next_starts[check_indices(indices, self.n)] = True

    def states(self) -> list[SessionState]:
        """Returns a snapshot of every session."""
        self._check_open()
        return [
            SessionState(
                config=self.configs[i],
                step=int(self._t[i]),
                episodes_completed=int(self._episodes[i]),
                shift=self._v[i].copy(),
                probe_pending=bool(self._pending[i]),
                response_mean_square=(float(self._mean_square[i]) if self._seeded[i] else None),
            )
            for i in range(self.n)
        ]

    def close(self) -> None:
        """Frees the sessions; later calls raise :class:`SessionNotFound`."""
        self._closed = True

    def __enter__(self) -> ReferenceBatch:
        """Returns self."""
        return self

    def __exit__(self, *exc: object) -> None:
        """Closes the sessions."""
        self.close()


class ReferenceSession:
    """One in-process ESA session with the API of :class:`esa_client.Session`.

    Args:
        config: The session config.
        session_id: The id; None = a random UUID.
    """

    def __init__(self, config: SessionConfig, session_id: str | None = None) -> None:
        """Creates the session at rest."""
        self._batch = ReferenceBatch([config], None if session_id is None else [session_id])
        self.id = self._batch.ids[0]
        self.config = config

    @property
    def step(self) -> int:
        """The current step t inside the episode."""
        return int(self._batch.steps[0])

    def probe(
        self,
        action: np.ndarray | Sequence[float],
        *,
        episode_start: bool = False,
        step: int | None = None,
        action_scale: float | Sequence[float] | np.ndarray | None = None,
    ) -> np.ndarray:
        """Returns the probe for the sampled ``action`` (see :meth:`ReferenceBatch.probe`)."""
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
        """Returns ``(probe, applied)`` (see :meth:`ReferenceBatch.probe_applied`)."""
        steps = None if step is None else [step]
        scales = (
            None
            if action_scale is None
            else np.broadcast_to(action_scale, (self.config.action_dim,))[None, :]
        )
        probes, applied = self._batch.probe_applied(
            np.asarray(action, dtype=np.float64)[None, :],
            [episode_start],
            steps=steps,
            action_scales=scales,
        )
        return probes[0], applied[0]

    def report(
        self, q_value: float, *, q_reference: float | None = None, step: int | None = None
    ) -> np.ndarray:
        """Takes Q at the probe; returns the improved action (see :meth:`ReferenceBatch.report`)."""
        references = None if q_reference is None else [q_reference]
        improved = self._batch.report(
            [q_value], q_references=references, steps=None if step is None else [step]
        )
        assert improved is not None
        action: np.ndarray = improved[0]
        return action

    def end_episode(self) -> int:
        """Ends the episode; returns the number of completed episodes."""
        return int(self._batch.end_episode()[0])

    def state(self) -> SessionState:
        """Returns a snapshot of the session."""
        return self._batch.states()[0]

    def close(self) -> None:
        """Frees the session."""
        self._batch.close()

    def __enter__(self) -> ReferenceSession:
        """Returns self."""
        return self

    def __exit__(self, *exc: object) -> None:
        """Closes the session."""
        self.close()


class ReferenceClient:
    """In-process stand-in for :class:`esa_client.EsaClient` (no server, no network)."""

    def create_session(
        self, config: SessionConfig, session_id: str | None = None
    ) -> ReferenceSession:
        """Creates one session."""
        return ReferenceSession(config, session_id)

    def create_batch(
        self,
        configs: SessionConfig | Sequence[SessionConfig],
        n: int | None = None,
        *,
        ids: Sequence[str] | None = None,
        use_stream: bool = False,
    ) -> ReferenceBatch:
        """Creates N sessions (one config for all, or one per session).

        ``use_stream`` is accepted for signature compatibility with
        :meth:`esa_client.EsaClient.create_batch`; there is no transport here.
        """
        return ReferenceBatch(as_batch_configs(configs, n), ids)

    def close(self) -> None:
        """Nothing to release; present for API symmetry."""

    def __enter__(self) -> ReferenceClient:
        """Returns self."""
        return self

    def __exit__(self, *exc: object) -> None:
        """Closes the client."""
        self.close()
