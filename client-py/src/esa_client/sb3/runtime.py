"""The ESA side of an SB3 learner: one session per env, the probe/report round trip, stats."""

from __future__ import annotations

import contextlib
from collections.abc import Callable

import numpy as np

from ..client import EsaClient
from ..config import EsaConfig
from ..env_dt import env_dt
from ..errors import EsaError

QFunction = Callable[[np.ndarray], np.ndarray]
"""Maps ``(k N, D)`` actions to ``(k N,)`` values at the N current observations tiled k times."""


class EsaRuntime:
    """Connection, sessions and statistics of one learner; never pickled with the model.

    Args:
        esa: The ESA hyperparameters.
        address: Server address, or None to spawn a private server for this learner.
        vec_env: The learner's VecEnv (gives the env count and ``dt``).
        low: Lower action bounds of the space ESA works in (shape ``(D,)``).
        high: Upper action bounds.
        use_stream: Carry the round trips on one StepStream (default; it measured about
            twice as fast per step as ProbeBatch/ReportBatch calls inside SB3's loop).
        improvement_every: Measure ``esa/improvement`` (the critic's Q at the improved
            minus at the sampled actions) on one step in this many. It costs a critic
            evaluation that training does not need, so it is sampled, not paid per step.
    """

    def __init__(
        self,
        esa: EsaConfig,
        address: str | None,
        vec_env: object,
        low: np.ndarray,
        high: np.ndarray,
        *,
        use_stream: bool = True,
        improvement_every: int = 8,
    ) -> None:
        """Connects (or spawns the server) and creates one session per env."""
        if improvement_every < 1:
            raise ValueError(f"expected improvement_every >= 1, got {improvement_every}")
        n_envs = vec_env.num_envs  # type: ignore[attr-defined]
        config = esa.session_config(low.size, env_dt(vec_env, esa.dt), low, high)
        self.client = EsaClient.spawn() if address is None else EsaClient(address)
        try:
            self.batch = self.client.create_batch(config, n_envs, use_stream=use_stream)
        except BaseException:
            self.client.close()
            raise
        self._improvement_every = improvement_every
        # Sums of mean |shift| and mean probe Q over the steps since the last record.
        self._sums = np.zeros(2)
        self._count = 0
        self._improvement_sum = 0.0
        self._improvement_count = 0
        self._calls = 0

    def improve(
        self, actions: np.ndarray, episode_starts: np.ndarray, q_fn: QFunction
    ) -> np.ndarray:
        """Runs one probe/report round for all envs and returns the improved actions.

        Args:
            actions: Sampled actions, shape ``(N, D)`` (any float dtype).
            episode_starts: True where an env starts a new episode, shape ``(N,)``.
            q_fn: The critic at the current observations.

        Returns:
            The improved actions, float64, shape ``(N, D)``.
        """
        sampled = np.asarray(actions, dtype=np.float64)
        probes = self.batch.probe(sampled, episode_starts)
        q_probe = np.asarray(q_fn(probes), dtype=np.float64)
        improved = self.batch.report(q_probe)
        self._sums += (np.abs(improved - sampled).mean(), q_probe.mean())
        self._count += 1
        if self._calls % self._improvement_every == 0:
            both = np.asarray(q_fn(np.concatenate([sampled, improved])), dtype=np.float64)
            n = len(sampled)
            self._improvement_sum += (both[n:] - both[:n]).mean()
            self._improvement_count += 1
        self._calls += 1
        return improved

    def record(self, logger: object) -> None:
        """Writes the mean stats since the last call to an SB3 logger and resets them."""
        if self._count == 0:
            return
        shift, probe_q = self._sums / self._count
        logger.record("esa/mean_abs_shift", shift)  # type: ignore[attr-defined]
        logger.record("esa/mean_probe_q", probe_q)  # type: ignore[attr-defined]
        if self._improvement_count:
            improvement = self._improvement_sum / self._improvement_count
            logger.record("esa/improvement", improvement)  # type: ignore[attr-defined]
        self._sums[:] = 0.0
        self._count = self._improvement_count = 0
        self._improvement_sum = 0.0

    def close(self) -> None:
        """Closes the sessions and the client (stopping a spawned server)."""
        # The sessions expire on their own if the server is already gone.
        with contextlib.suppress(EsaError):
            self.batch.close()
        self.client.close()
