"""Bootstrap statistics of runs over seeds, with ``rliable`` (Agarwal et al., NeurIPS 2021).

* ``probability_of_improvement``: the probability that a run of one method beats a run of
  another (``P(X > Y)``, ties counted half), with its 95 % stratified-bootstrap CI;
* ``verdict``: **better** when that CI lies above 0.5, **worse** when it lies below,
  **equal** otherwise (no significant difference at this number of seeds);
* ``iqm_curve``: the IQM over runs at every evaluation of a learning curve, with its 95 %
  stratified-bootstrap CI, as the learning-curve figures draw it.
"""

from __future__ import annotations

import numpy as np
from rliable import library as rly
from rliable import metrics
from scipy.stats import trim_mean

REPS = 2000
"""Bootstrap resamples (rliable's default is 50,000; 2,000 keeps the report fast)."""

SEED = 0
"""The bootstrap's random seed: the statistics are reproducible from the CSVs."""


def _iqm_per_point(scores: np.ndarray) -> np.ndarray:
    # rliable's aggregate_iqm (scipy's trim_mean, 25 % off each end, over runs and tasks) at
    # every point of the last axis in one call: a loop of aggregate_iqm over the points
    # gives the same numbers, but 2,000 resamples of 500-point curves made it take minutes.
    return np.asarray(trim_mean(scores.reshape(-1, scores.shape[-1]), 0.25, axis=0))


def iqm_curve(scores: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """IQM over runs at every point of a curve, with its 95 % stratified-bootstrap CI.

    rliable's percentile bootstrap with ``REPS`` resamples, seeded with ``SEED`` on every
    call (so a figure does not depend on what was drawn before it). A resample draws whole
    runs, as rliable's sample-efficiency curves do.

    Args:
        scores: shape (runs, points), finite: one row per seed, one column per x value.

    Returns:
        The IQM and the CI's lower and upper ends, each of shape (points,).

    Raises:
        ValueError: if ``scores`` is not a non-empty 2-D array of finite values.
    """
    scores = np.asarray(scores, dtype=float)
    if scores.ndim != 2 or scores.size == 0:
        raise ValueError(f"expected a non-empty array (runs, points), got shape {scores.shape}")
    if not np.isfinite(scores).all():
        bad = int((~np.isfinite(scores)).sum())
        raise ValueError(f"expected finite scores, got {bad} NaN or infinite value(s)")
    np.random.seed(SEED)  # rliable's bootstrap draws from numpy's global generator
    point, ci = rly.get_interval_estimates({"curve": scores[:, None, :]}, _iqm_per_point, reps=REPS)
    return point["curve"], ci["curve"][0], ci["curve"][1]


def probability_of_improvement(x: np.ndarray, y: np.ndarray) -> tuple[float, float, float]:
    """``P(X > Y)`` of runs of x over runs of y, with its stratified-bootstrap 95 % CI."""
    point, ci = rly.get_interval_estimates(
        {"pair": (x[:, None], y[:, None])},
        lambda a, b: np.array([metrics.probability_of_improvement(a, b)]),
        reps=REPS,
    )
    return float(point["pair"][0]), float(ci["pair"][0, 0]), float(ci["pair"][1, 0])


def verdict(low: float, high: float) -> str:
    """``better``/``worse`` when the CI of P(improvement) excludes 0.5, else ``equal``."""
    if low > 0.5:
        return "better"
    if high < 0.5:
        return "worse"
    return "equal"
