"""Confirmation verdicts: each ESA arm against its baseline and its gradient control.

Per (env, arm, reference) over the seeds both finished: the probability that a run of
the arm beats a run of the reference on AUC, ``P(X > Y)`` with its stratified-bootstrap
95 % CI (rliable), and the two-sided Mann-Whitney U test of ``P(X > Y) = 0.5`` (the
same quantity). The p-values of one algorithm family (all its envs and comparisons)
are Holm-corrected together; a verdict is **better** / **worse** when the corrected
p-value is below 0.05, in the direction of ``P(X > Y)``, else **equal**.

Aggregated over envs per family: ``P(X > Y)`` averaged over the envs (rliable's
multi-task probability of improvement), on the seeds every env finished.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd
from rliable import library as rly
from rliable import metrics
from scipy.stats import mannwhitneyu

from esa_client.compare.reliability import REPS, SEED, probability_of_improvement, verdict
from esa_client.compare.tables import per_seed

ALPHA = 0.05


@dataclass(frozen=True)
class Comparison:
    """One arm against one reference, in one family.

    Attributes:
        family: the Holm family (the algorithm: ``ppo``, ``sac``, ``td3``).
        method: the arm.
        reference: the baseline or the gradient control.
        kind: ``baseline`` or ``gradient control``.
    """

    family: str
    method: str
    reference: str
    kind: str


def auc_by_seed(frame: pd.DataFrame, env: str, method: str) -> pd.Series:
    """AUC per seed of one (env, method); empty if nothing finished."""
    runs = frame[(frame.env == env) & (frame.method == method)]
    if runs.empty:
        return pd.Series(dtype=float)
    table = per_seed(runs, np.nan)
    return pd.Series(table.auc.to_numpy(float), index=table.seed.to_numpy(int))


def holm(pvalues: Sequence[float]) -> np.ndarray:
    """Holm's step-down adjusted p-values (family-wise error), in the input order."""
    p = np.asarray(pvalues, dtype=float)
    order = np.argsort(p)
    adjusted = np.empty_like(p)
    running = 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (len(p) - rank) * p[i]))
        adjusted[i] = running
    return adjusted


def verdict_table(
    frame: pd.DataFrame,
    envs: Sequence[str],
    comparisons: Sequence[Comparison],
    labels: Mapping[str, str],
    seeds: Sequence[int] | None = None,
) -> pd.DataFrame:
    """One row per (env, comparison) with runs on common seeds, Holm-corrected per family."""
    np.random.seed(SEED)  # rliable's bootstrap draws from numpy's global generator
    rows = []
    for env in envs:
        for c in comparisons:
            x, y = auc_by_seed(frame, env, c.method), auc_by_seed(frame, env, c.reference)
            common = x.index.intersection(y.index)
            if seeds is not None:
                common = common.intersection(pd.Index(seeds))
            if len(common) < 2:
                continue
            xs, ys = x[common].to_numpy(), y[common].to_numpy()
            p_better, low, high = probability_of_improvement(xs, ys)
            rows.append(
                {
                    "family": c.family,
                    "env": env,
                    "method": labels.get(c.method, c.method),
                    "against": f"{labels.get(c.reference, c.reference)} ({c.kind})",
                    "seeds": len(common),
                    "mean AUC (arm / reference)": f"{xs.mean():.1f} / {ys.mean():.1f}",
                    "P(arm better) [95% CI]": f"{p_better:.2f} [{low:.2f}, {high:.2f}]",
                    "_p": float(mannwhitneyu(xs, ys, alternative="two-sided").pvalue),
                    "_direction": p_better - 0.5,
                }
            )
    table = pd.DataFrame(rows)
    if table.empty:
        return table
    table["Holm p"] = np.nan
    for _, index in table.groupby("family").groups.items():
        table.loc[index, "Holm p"] = holm(table.loc[index, "_p"].tolist())
    table["verdict"] = [
        ("**better**" if d > 0 else "**worse**") if p < ALPHA else "equal"
        for p, d in zip(table["Holm p"], table["_direction"], strict=True)
    ]
    table["Holm p"] = table["Holm p"].map(lambda p: f"{p:.3f}")
    return table.drop(columns=["_p", "_direction"])


def aggregate_table(
    frame: pd.DataFrame,
    envs_of: Mapping[str, Sequence[str]],
    comparisons: Sequence[Comparison],
    labels: Mapping[str, str],
) -> pd.DataFrame:
    """Per comparison, ``P(X > Y)`` averaged over the family's envs, on seeds all finished."""
    np.random.seed(SEED)
    rows = []
    for c in comparisons:
        envs = envs_of[c.family]
        xs = [auc_by_seed(frame, env, c.method) for env in envs]
        ys = [auc_by_seed(frame, env, c.reference) for env in envs]
        common = pd.Index(sorted(set.intersection(*(set(s.index) for s in xs + ys))))
        if len(common) < 2:
            continue
        x = np.stack([s[common].to_numpy() for s in xs], axis=1)
        y = np.stack([s[common].to_numpy() for s in ys], axis=1)
        point, ci = rly.get_interval_estimates(
            {"pair": (x, y)},
            lambda a, b: np.array([metrics.probability_of_improvement(a, b)]),
            reps=REPS,
        )
        low, high = float(ci["pair"][0, 0]), float(ci["pair"][1, 0])
        rows.append(
            {
                "family": c.family,
                "method": labels.get(c.method, c.method),
                "against": f"{labels.get(c.reference, c.reference)} ({c.kind})",
                "envs": len(envs),
                "seeds": len(common),
                "P(arm better) over envs [95% CI]": (
                    f"{float(point['pair'][0]):.2f} [{low:.2f}, {high:.2f}]"
                ),
                "CI verdict": verdict(low, high),
            }
        )
    return pd.DataFrame(rows)


def diagnostics_table(
    frame: pd.DataFrame,
    meta: pd.DataFrame,
    envs: Sequence[str],
    methods: Sequence[str],
    labels: Mapping[str, str],
    crash_window: int = 20_000,
) -> pd.DataFrame:
    """Final-return IQM, ESA's shift, KL and gate, training crashes and episode shape.

    Args:
        frame: the evaluation rows of the study (``RunStore.load``).
        meta: one row per run with the sidecar's ``mean esa/...`` fields.
        envs: envs in order.
        methods: methods in order.
        labels: method -> display name.
        crash_window: the crash rate counts training episodes that ended in these first steps.
    """
    rows = []
    for env in envs:
        for method in methods:
            runs = frame[(frame.env == env) & (frame.method == method)]
            if runs.empty:
                continue
            finals = per_seed(runs, np.nan).final.to_numpy(float)
            last = runs.sort_values("step").groupby("seed").tail(1)
            early = runs[runs.step <= crash_window].sort_values("step").groupby("seed").tail(1)
            info = meta[(meta.env == env) & (meta.method == method)]
            row = {
                "env": env,
                "method": labels.get(method, method),
                "seeds": runs.seed.nunique(),
                "final return IQM": f"{metrics.aggregate_iqm(finals):.1f}",
            }
            for key, name in (
                ("mean esa/shift_over_std", "mean |v|/sigma"),
                ("mean esa/kl_per_dim", "KL per dim"),
                ("mean esa/gate_correlation", "gate corr."),
                ("mean train/approx_kl", "PPO approx. KL"),
            ):
                values = info[key].dropna() if key in info else pd.Series(dtype=float)
                row[name] = f"{values.mean():.3g}" if len(values) else ""
            if "train_episodes" in runs:
                episodes = early.train_episodes.sum()
                row[f"crash rate, first {crash_window // 1000}k"] = (
                    f"{early.train_crashes.sum() / episodes:.2f}" if episodes else ""
                )
                length = last.train_length_sum.sum()
                row["train return / step"] = (
                    f"{last.train_return_sum.sum() / length:.3f}" if length else ""
                )
                row["train episode length"] = (
                    f"{length / last.train_episodes.sum():.0f}" if last.train_episodes.sum() else ""
                )
            rows.append(row)
    return pd.DataFrame(rows)


VERDICT_COLUMNS = ("mean AUC (arm / reference)", "P(arm better) [95% CI]", "Holm p", "verdict")
"""The columns of :func:`verdict_table` that :func:`compact_table` puts in one cell."""


def _brief(row: pd.Series, suffix: str) -> str:
    """One metric's verdict in a cell: mean AUCs, P(arm better) with its CI, Holm p, verdict."""
    auc, p_better, holm_p, word = (row[f"{column}{suffix}"] for column in VERDICT_COLUMNS)
    arm, reference = (float(x) for x in str(auc).split(" / "))
    return f"{arm:.0f} vs {reference:.0f}, P = {p_better}, p = {holm_p}: {word}"


def compact_table(primary: pd.DataFrame, whole: pd.DataFrame) -> pd.DataFrame:
    """Both metrics' verdicts side by side, one row per (env, arm, reference).

    Args:
        primary: :func:`verdict_table` on the first third of the budget.
        whole: :func:`verdict_table` on the whole curve.

    Returns:
        Columns env, arm, against, seeds and one cell per metric (mean AUC of arm and
        reference, ``P(arm better)`` with its CI, Holm p, verdict); empty if either is.
    """
    if primary.empty or whole.empty:
        return pd.DataFrame()
    keys = ["family", "env", "method", "against", "seeds"]
    merged = primary.merge(whole, on=keys, suffixes=(" first", " whole"))
    return pd.DataFrame(
        {
            "env": merged.env,
            "arm": merged.method,
            "against": merged.against,
            "seeds": merged.seeds,
            "AUC over the first third (primary)": merged.apply(_brief, axis=1, args=(" first",)),
            "AUC over the whole curve": merged.apply(_brief, axis=1, args=(" whole",)),
        }
    )


def better_and_worse(
    primary: pd.DataFrame, whole: pd.DataFrame, arm: str
) -> tuple[set[str], set[str]]:
    """The envs where ``arm`` helped, and those where it harmed (a study's success rule).

    Args:
        primary: verdicts on the primary metric (first-third AUC).
        whole: verdicts on the whole curve.
        arm: the ESA arm's label.

    Returns:
        ``(helped, harmed)``: the envs where ``arm`` is **better** than both its baseline
        and its placebo on ``primary``, and those where it is **worse** than its baseline on
        ``whole``.
    """
    mine = primary[primary.method == arm]
    better = [
        set(mine[mine.against.str.endswith(f"({kind})") & (mine.verdict == "**better**")].env)
        for kind in ("baseline", "placebo")
    ]
    harmed = whole[
        (whole.method == arm)
        & whole.against.str.endswith("(baseline)")
        & (whole.verdict == "**worse**")
    ]
    return better[0] & better[1], set(harmed.env)
