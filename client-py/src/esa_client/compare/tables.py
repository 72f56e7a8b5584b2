"""Seed statistics and the Markdown summary tables of the RL studies.

Per (env, method), over seeds (mean +- standard error):

* final return: the last evaluation's mean return;
* AUC: area under the evaluation curve divided by the step span, i.e. the
  average return over training (rewards fast learners);
* steps to threshold: first evaluated step whose return reaches the env's
  threshold (median over the seeds that reached it, and how many did);
* train s: training wall-clock seconds, evaluation excluded;
* overhead vs base: mean training wall-clock and CPU time of an ESA method
  divided by those of its base method on the same env (``ppo_esa`` / ``ppo``,
  ``sac_esa`` / ``sac``; the ablations compare every variant with PPO).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import pandas as pd


def _mean_sem(values: Sequence[float], fmt: str = "{:.1f}") -> str:
    array = np.asarray(values, dtype=float)
    sem = array.std(ddof=1) / np.sqrt(len(array)) if len(array) > 1 else 0.0
    return f"{fmt.format(array.mean())} ± {fmt.format(sem)}"


def _trapezoid(y: np.ndarray, x: np.ndarray) -> float:
    return float(np.sum((y[1:] + y[:-1]) / 2 * np.diff(x)))


def per_seed(runs: pd.DataFrame, threshold: float) -> pd.DataFrame:
    """One row per seed: final return, AUC, steps to ``threshold``, training times."""
    rows = []
    for seed, run in runs.groupby("seed"):
        run = run.sort_values("step")
        steps, returns = run.step.to_numpy(float), run.return_mean.to_numpy(float)
        span = steps[-1] - steps[0]
        reached = steps[returns >= threshold]
        rows.append(
            {
                "seed": seed,
                "final_step": steps[-1],
                "final": returns[-1],
                "auc": _trapezoid(returns, steps) / span if span > 0 else returns[-1],
                "to_threshold": reached[0] if reached.size else np.nan,
                "train_seconds": run.train_seconds.iloc[-1],
                "train_cpu_seconds": run.train_cpu_seconds.iloc[-1],
            }
        )
    return pd.DataFrame(rows)


def summary(
    frame: pd.DataFrame,
    envs: Sequence[str],
    methods: Sequence[str],
    labels: Mapping[str, str],
    thresholds: Mapping[str, float],
    baselines: Mapping[str, str],
) -> pd.DataFrame:
    """The summary table (one row per env and method that has finished runs)."""
    rows = []
    train_time: dict[tuple[str, str], tuple[float, float]] = {}
    per_method: dict[tuple[str, str], pd.DataFrame] = {}
    for env in envs:
        for method in methods:
            runs = frame[(frame.env == env) & (frame.method == method)]
            if not runs.empty:
                seeds = per_seed(runs, thresholds.get(env, np.nan))
                per_method[env, method] = seeds
                train_time[env, method] = (
                    float(seeds.train_seconds.mean()),
                    float(seeds.train_cpu_seconds.mean()),
                )
    for (env, method), seeds in per_method.items():
        reached = seeds.to_threshold.dropna()
        base = baselines.get(method)
        overhead = ""
        if base is not None and (env, base) in train_time:
            (wall, cpu), (base_wall, base_cpu) = train_time[env, method], train_time[env, base]
            overhead = f"{wall / base_wall:.2f}x / {cpu / base_cpu:.2f}x"
        rows.append(
            {
                "env": env,
                "method": labels.get(method, method),
                "seeds": len(seeds),
                "steps": int(seeds.final_step.max()),
                "final return": _mean_sem(seeds.final),
                "AUC (mean return)": _mean_sem(seeds.auc),
                "threshold": f"{thresholds.get(env, np.nan):g}",
                "steps to threshold": (
                    f"{int(reached.median())} ({len(reached)}/{len(seeds)})"
                    if len(reached)
                    else f"not reached (0/{len(seeds)})"
                ),
                "train s (wall / CPU)": (
                    f"{seeds.train_seconds.mean():.1f} / {seeds.train_cpu_seconds.mean():.1f}"
                ),
                "overhead vs base (wall / CPU)": overhead,
            }
        )
    return pd.DataFrame(rows)


EXPLORATION_STATS = {
    "esa/mean_abs_shift": "mean abs(applied - sampled action)",
    "esa/shift_over_std": "mean abs(v) / sigma",
    "esa/kl_per_dim": "KL(behaviour ‖ pi) per dim",
    "esa/clipped_fraction": "fraction of steps clipped",
    "esa/active": "ESA active (gate open)",
    "esa/gate_correlation": "gate: critic rank correlation",
    "esa/improvement": "critic's Q(applied) - Q(sampled)",
    "param_noise/sigma": "param-noise sigma",
    "param_noise/distance": "param-noise action distance",
}
"""Training-log statistics shown per method (means over training, then over seeds)."""


def exploration_stats(
    log: pd.DataFrame, envs: Sequence[str], methods: Sequence[str], labels: Mapping[str, str]
) -> pd.DataFrame:
    """What the exploration add-ons did during training (ESA shifts, noise scale)."""
    keys = [key for key in EXPLORATION_STATS if key in log.columns]
    rows = []
    for env in envs:
        for method in methods:
            runs = log[(log.env == env) & (log.method == method)].dropna(subset=keys, how="all")
            if runs.empty or not keys:
                continue
            per_seed = runs.groupby("seed")[keys].mean()
            row = {"env": env, "method": labels.get(method, method)}
            for key in keys:
                values = per_seed[key].dropna()
                row[EXPLORATION_STATS[key]] = _mean_sem(values, "{:.4g}") if len(values) else ""
            rows.append(row)
    return pd.DataFrame(rows)


def _cell(value: object) -> str:
    # A bare "|" inside a cell ends the cell: escaped, it renders as itself (GFM, mkdocs).
    return str(value).replace("|", "\\|")


def to_markdown(table: pd.DataFrame) -> str:
    """A GitHub-flavoured Markdown table (no extra dependency); ``|`` in a cell is escaped."""
    header = "| " + " | ".join(map(_cell, table.columns)) + " |"
    rule = "|" + "---|" * len(table.columns)
    body = ["| " + " | ".join(map(_cell, row)) + " |" for row in table.itertuples(index=False)]
    return "\n".join([header, rule, *body])
