"""Per-env statistics the way the field now expects them (Agarwal et al., NeurIPS 2021).

With ``rliable``, per (env, method), over the seeds:

* IQM and mean of the AUC (average evaluation return over training), each with a
  95 % stratified-bootstrap confidence interval;
* the probability that a run of the method beats a run of its baseline
  (``P(X > Y)`` on AUC, ties counted half), with its bootstrap CI;
* a verdict: **better** when that CI lies above 0.5, **worse** when it lies below,
  **equal** otherwise (no significant difference at this number of seeds).

The learning-curve figures draw the same IQM and CI at every evaluation (``iqm_curve``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import numpy as np
import pandas as pd
from rliable import library as rly
from rliable import metrics
from scipy.stats import trim_mean

from esa_experiments.algorithms import BASELINE_OF, LABELS
from esa_experiments.runs import RunStore
from esa_experiments.tables import per_seed, to_markdown

REPS = 2000
"""Bootstrap resamples (rliable's default is 50,000; 2,000 keeps the report fast)."""

SEED = 0
"""The bootstrap's random seed: the statistics are reproducible from the CSVs."""


def _interval(
    scores: np.ndarray, aggregate: Callable[[np.ndarray], float]
) -> tuple[float, float, float]:
    point, ci = rly.get_interval_estimates(
        {"m": scores[:, None]}, lambda x: np.array([aggregate(x)]), reps=REPS
    )
    return float(point["m"][0]), float(ci["m"][0, 0]), float(ci["m"][1, 0])


def _iqm_per_point(scores: np.ndarray) -> np.ndarray:
    # rliable's aggregate_iqm (scipy's trim_mean, 25 % off each end, over runs and tasks) at
    # every point of the last axis in one call: a loop of aggregate_iqm over the points
    # gives the same numbers, but 2,000 resamples of 500-point curves made it take minutes.
    return np.asarray(trim_mean(scores.reshape(-1, scores.shape[-1]), 0.25, axis=0))


def iqm_curve(scores: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """IQM over runs at every point of a curve, with its 95 % stratified-bootstrap CI.

    The statistic of the verdicts, pointwise: rliable's percentile bootstrap with ``REPS``
    resamples, seeded with ``SEED`` on every call (so a figure does not depend on what was
    drawn before it). A resample draws whole runs, as rliable's sample-efficiency curves do.

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


def statistics(
    frame: pd.DataFrame,
    envs: Sequence[str],
    methods: Sequence[str],
    labels: Mapping[str, str] = LABELS,
    baselines: Mapping[str, str] = BASELINE_OF,
) -> pd.DataFrame:
    """One row per (env, method) with finished runs: IQM, mean, P(improvement), verdict."""
    np.random.seed(SEED)  # rliable's bootstrap draws from numpy's global generator
    auc: dict[tuple[str, str], np.ndarray] = {}
    for env in envs:
        for method in methods:
            runs = frame[(frame.env == env) & (frame.method == method)]
            if not runs.empty:
                auc[env, method] = per_seed(runs, np.nan).auc.to_numpy(float)
    rows = []
    for (env, method), scores in auc.items():
        iqm = _interval(scores, metrics.aggregate_iqm)
        mean = _interval(scores, metrics.aggregate_mean)
        row = {
            "env": env,
            "method": labels.get(method, method),
            "seeds": len(scores),
            "IQM AUC [95% CI]": f"{iqm[0]:.1f} [{iqm[1]:.1f}, {iqm[2]:.1f}]",
            "mean AUC [95% CI]": f"{mean[0]:.1f} [{mean[1]:.1f}, {mean[2]:.1f}]",
            "P(better than base) [95% CI]": "",
            "verdict": "",
        }
        base = baselines.get(method)
        if base is not None and (env, base) in auc:
            p, low, high = probability_of_improvement(scores, auc[env, base])
            row["P(better than base) [95% CI]"] = f"{p:.2f} [{low:.2f}, {high:.2f}]"
            word = verdict(low, high)
            relation = "to" if word == "equal" else "than"
            row["verdict"] = f"**{word}** {relation} {labels.get(base, base)}"
        rows.append(row)
    return pd.DataFrame(rows)


def reliability_section(
    store: RunStore,
    envs: Sequence[str],
    methods: Sequence[str],
    labels: Mapping[str, str] | None = None,
    baselines: Mapping[str, str] | None = None,
) -> str:
    """The Markdown statistics table of a study (also written to ``statistics.md``)."""
    frame = store.load()
    table = to_markdown(
        statistics(
            frame, envs, methods, {**LABELS, **(labels or {})}, {**BASELINE_OF, **(baselines or {})}
        )
    )
    text = (
        "Per env, over seeds (`rliable`, 95 % stratified-bootstrap CIs, "
        f"{REPS} resamples, seed {SEED}); AUC = average evaluation return over training; "
        "P(better than base) = probability that a run beats a run of the baseline on AUC; "
        "verdict: better / worse when that CI excludes 0.5, else equal:\n\n"
        f"{table}\n"
    )
    (store.artifact("statistics.md")).write_text(table + "\n")
    return text
