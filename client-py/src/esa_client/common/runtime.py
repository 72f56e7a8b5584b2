"""The ESA side of a learner (SB3 or RLlib): one session per env, one round trip per step."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable
from typing import Any, Literal, Protocol, TypeVar, get_args

import numpy as np

from .._native import StepStats
from ..client import EsaClient
from ..config import EsaConfig, SessionConfig
from ..errors import EsaError, ServerUnavailable
from ..transports.base import SMALLEST_SCALE, LinearCritic, QuadraticCritic
from .controls import REPORT_EVERY

_log = logging.getLogger("esa_client")

OnUnavailable = Literal["raise", "skip"]
"""What a learner does once the server stayed unreachable past the client's reconnect time."""

ON_UNAVAILABLE: tuple[OnUnavailable, ...] = get_args(OnUnavailable)


def check_on_unavailable(on_unavailable: str) -> OnUnavailable:
    """Returns ``on_unavailable`` if it is ``"raise"`` or ``"skip"``."""
    if on_unavailable not in ON_UNAVAILABLE:
        raise ValueError(f"expected on_unavailable in {ON_UNAVAILABLE}, got {on_unavailable!r}")
    return on_unavailable


_Ran = TypeVar("_Ran")

QFunction = Callable[[np.ndarray], np.ndarray]
"""Maps ``(k N, D)`` actions to ``(k N,)`` values at the N current observations tiled k times."""


class LoggerLike(Protocol):
    """What the runtime writes to: an SB3 ``Logger`` (or anything with its ``record``)."""

    def record(self, key: str, value: Any) -> None:
        """Records one value under ``key``."""


class EsaRuntime:
    """The sessions and statistics of one learner, on a client it does not own.

    Each step is one :meth:`SessionBatch.step` of the envs' batch on a StepStream. Lost
    sessions are recreated (``esa/sessions_restored``); a lost server is ridden out as the
    batch does, then ``on_unavailable`` decides: ``"raise"`` raises ``ServerUnavailable``,
    ``"skip"`` applies the samples unchanged until the next episode start of any env, where
    it tries the server again (``esa/unavailable_steps``, one per env).

    Args:
        esa: The ESA hyperparameters.
        client: Where the sessions live; the caller closes it (:meth:`close` closes only
            the sessions).
        config: The sessions' config (``EsaConfig.session_config`` for the env).
        n_envs: How many sessions (one per env).
        clip_low: Bounds the environment clips to, for the clipped-action statistic.
        clip_high: See ``clip_low``.
        on_unavailable: ``"raise"`` (default) or ``"skip"``, see above.

    Raises:
        ValueError: If ``on_unavailable`` is unknown.
    """

    def __init__(
        self,
        esa: EsaConfig,
        client: EsaClient,
        config: SessionConfig,
        n_envs: int,
        clip_low: np.ndarray,
        clip_high: np.ndarray,
        *,
        on_unavailable: OnUnavailable = "raise",
    ) -> None:
        """Creates the ``n_envs`` sessions on ``client``."""
        self.on_unavailable = check_on_unavailable(on_unavailable)
        self.esa = esa
        self.client = client
        self.batch = client.create_batch(config, n_envs, use_stream=True)
        self._stats = StepStats(
            [float(v) for v in clip_low.reshape(-1)], [float(v) for v in clip_high.reshape(-1)]
        )
        self._bounds = (config.vector("action_low"), config.vector("action_high"))
        self._calls = 0
        self._skipping = False  # ESA off after the server stayed unreachable ("skip")

    def step(
        self,
        sampled: np.ndarray,
        episode_starts: np.ndarray,
        q_fn: QFunction | LinearCritic | QuadraticCritic,
        policy_std: np.ndarray | None = None,
        *,
        strength: float = 1.0,
    ) -> np.ndarray:
        """Runs Algorithm 1's step for all envs and returns the actions to apply.

        Args:
            sampled: The policy's samples a_t, shape ``(N, D)`` (any float dtype).
            episode_starts: True where an env starts a new episode, shape ``(N,)``.
            q_fn: The critic at the current observations, as :meth:`SessionBatch.step` takes it.
            policy_std: The policy's standard deviation, shape ``(N, D)``; sent as the
                action scale when ``use_policy_std`` (else 1).
            strength: ESA's strength ``f`` in [0, 1] (:meth:`EsaConfig.strength`): scales the
                action scale sent; at 0 no session steps (``esa/faded_steps``).

        Returns:
            ``a_t + v(t)`` (clipped to the session's bounds, if it has any), float64,
            shape ``(N, D)``.
        """
        a = np.asarray(sampled, dtype=np.float64)
        if policy_std is not None:
            # A saturated squashed policy or an underflowed std has sigma = 0, which the
            # contract rejects; the smallest positive float32 changes no non-zero std and
            # still keeps v at 0 there.
            policy_std = np.maximum(policy_std, SMALLEST_SCALE)
        scale = policy_std if self.esa.use_policy_std else None
        if strength < 1.0:
            if strength <= 0.0:
                return self._without_esa(a, "faded_steps")
            scale = strength * (np.ones_like(a) if scale is None else scale)
        applied = self._attempt(
            episode_starts,
            lambda starts: self.batch.step(
                a, q_fn, starts, action_scales=scale, paired=self.esa.paired_response
            )[1],
        )
        if applied is None:
            return self._without_esa(a, "unavailable_steps")
        n = len(a)
        self._stats.add_step(a, applied, policy_std)
        # esa/improvement (Q at the applied minus at the sampled actions): a critic call
        # that training does not need, so on one step in REPORT_EVERY.
        if self._calls % REPORT_EVERY == 0:
            both = np.asarray(q_fn(np.concatenate([a, applied])), dtype=np.float64)
            self._stats.add_improvement(float((both[n:] - both[:n]).mean()))
        self._calls += 1
        return applied

    def _attempt(
        self, episode_starts: np.ndarray, run: Callable[[np.ndarray | None], _Ran]
    ) -> _Ran | None:
        """``run(episode_starts)`` under ``on_unavailable``, counting recreated sessions.

        Once the batch's recovery gives up, ``"skip"`` returns None until an episode starts.
        """
        batch = self.batch
        restored = batch.sessions_restored
        try:
            if self._skipping:
                if not np.any(episode_starts):
                    return None
                batch.restore()
                self._skipping = False
                _log.warning("esa server at %s reachable again: ESA resumes", self.client.address)
                return run(None)
            return batch.recovery.rerun_lost(run, episode_starts)
        except ServerUnavailable as err:
            if self.on_unavailable == "raise":
                raise
            if not self._skipping:
                _log.warning("%s; continuing without ESA until the next episode start", err.message)
            self._skipping = True
            return None
        finally:
            if batch.sessions_restored > restored:
                self._stats.add_count("sessions_restored", batch.sessions_restored - restored)

    def _without_esa(self, sampled: np.ndarray, why: str) -> np.ndarray:
        """The samples clipped to the sessions' bounds, counted under ``why``: no ESA."""
        self._stats.add_count(why, len(sampled))
        applied: np.ndarray = np.asarray(np.clip(sampled, *self._bounds), dtype=np.float64)
        return applied

    def record(self, logger: LoggerLike) -> None:
        """Writes the mean stats since the last call to an SB3 logger and resets them."""
        for key, value in self._stats.means().items():
            logger.record(f"esa/{key}", value)
        self._stats.reset()

    def close(self) -> None:
        """Closes the sessions (the client stays open); a gone server lets them expire."""
        with contextlib.suppress(EsaError):
            self.batch.close()
