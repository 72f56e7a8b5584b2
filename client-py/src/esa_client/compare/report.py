"""What a comparison answers with: curves, a summary, the verdicts and their provenance.

Written into the comparison's folder from its finished runs, with the statistics of the
project's own studies (:mod:`esa_client.compare.verdicts`):

* ``learning_curves.png``: IQM over seeds with its 95 % bootstrap CI, every seed thin;
* ``summary.md``: final return, AUC and training time per arm (mean ± standard error);
* ``verdicts.md``: every comparison on both metrics, and the answer in one sentence;
* ``RESULTS.md``: all of it on one page, with the rules and the command;
* ``provenance.json``: versions, host, command, and digests of the rules and the runs.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import sys
from datetime import datetime, timezone
from importlib import metadata
from math import comb

import numpy as np
import pandas as pd

from esa_client.compare.plotting import Panel, learning_curves
from esa_client.compare.rules import Rules
from esa_client.compare.runs import RunFolder, atomic_write_text
from esa_client.compare.tables import exploration_stats, summary, to_markdown
from esa_client.compare.verdicts import ALPHA, Comparison, compact_table, verdict_table

TOO_FEW = "too few seeds to tell"
PACKAGES = ("esa-client", "stable-baselines3", "torch", "gymnasium", "mujoco", "numpy", "rliable")


def comparisons(rules: Rules) -> list[Comparison]:
    """Each ESA arm against the baseline, and ESA against each control it has."""
    pairs = [(arm, "baseline", "baseline") for arm in rules.arms if arm != "baseline"]
    pairs += [("esa", control, f"{control} control") for control in ("placebo", "gradient")]
    return [
        Comparison(rules.algo, arm, reference, kind)
        for arm, reference, kind in pairs
        if arm in rules.arms and reference in rules.arms
    ]


def first_part(frame: pd.DataFrame, total_steps: int, fraction: float = 1 / 3) -> pd.DataFrame:
    """The evaluation rows within the first ``fraction`` of the budget (the primary metric)."""
    return frame[frame.step <= fraction * total_steps]


def could_decide(seeds: int, tests: int) -> bool:
    """Whether ``seeds`` runs per arm could give Holm p < ALPHA among ``tests`` comparisons.

    The smallest two-sided Mann-Whitney p of two samples of n is ``2 / C(2n, n)`` (all of
    one arm above all of the other); Holm multiplies the smallest p by the number of tests.
    """
    return tests * 2 / comb(2 * seeds, seeds) < ALPHA


def judged(frame: pd.DataFrame, rules: Rules) -> dict[str, pd.DataFrame]:
    """The verdict tables of both metrics, with ``too few seeds to tell`` where that holds."""
    labels = {arm: rules.label(arm) for arm in rules.arms}
    tables = {
        "first": verdict_table(
            first_part(frame, rules.steps), [rules.env], comparisons(rules), labels
        ),
        "whole": verdict_table(frame, [rules.env], comparisons(rules), labels),
    }
    for table in tables.values():
        if table.empty:
            continue
        undecidable = [not could_decide(int(n), len(table)) for n in table.seeds]
        table.loc[undecidable, "verdict"] = TOO_FEW
    return tables


def answer(primary: pd.DataFrame, rules: Rules) -> str:
    """The comparison's answer in one sentence, from the primary metric's verdicts."""
    if primary.empty:
        return "No answer yet: no comparison has two seeds finished by both arms."
    esa = rules.label("esa")

    def verdict(reference: str) -> str | None:
        rows = primary[(primary.method == esa) & primary.against.str.startswith(reference)]
        return None if rows.empty else str(rows.verdict.iloc[0])

    against_baseline = verdict(rules.label("baseline"))
    against_placebo = verdict(rules.label("placebo"))
    if TOO_FEW in (against_baseline, against_placebo):
        return f"Too few seeds to tell whether {esa} helps: run more seeds (--seeds)."
    if against_baseline is None:
        return f"No answer: {esa} and the baseline have no two common seeds yet."
    if "worse" in against_baseline:
        return f"{esa} learns significantly slower than the baseline on this task."
    if "better" in against_baseline and against_placebo is not None:
        if "better" in against_placebo:
            return f"{esa} helps: it beats both the baseline and the placebo."
        return (
            f"{esa} beats the baseline but not the placebo: the gain comes from perturbing "
            "the actions, not from seeking higher Q."
        )
    if "better" in against_baseline:
        return f"{esa} beats the baseline; without a placebo arm its cause is untested."
    return f"No evidence that {esa} helps on this task: it learns as fast as the baseline."


def _versions() -> dict[str, str]:
    versions = {"python": sys.version.split()[0]}
    for package in PACKAGES:
        try:
            versions[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            versions[package] = "not installed"
    return versions


def runs_digest(folder: RunFolder) -> str:
    """A hash of every finished run's CSV: the report is up to date when it is unchanged."""
    digest = hashlib.sha256()
    for path in sorted(folder.runs_dir.glob("*.csv")):
        digest.update(path.name.encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


def write_provenance(folder: RunFolder, rules: Rules, command: str, digest: str) -> None:
    """``provenance.json``: what made the folder's report, and where."""
    provenance = {
        "command": command,
        "written": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "versions": _versions(),
        "host": {
            "node": platform.node(),
            "platform": platform.platform(),
            "machine": platform.machine(),
            "processor": platform.processor(),
            "cpus": os.cpu_count(),
        },
        "rules_sha256": hashlib.sha256(rules.to_json().encode()).hexdigest()[:16],
        "runs_sha256": digest,
    }
    atomic_write_text(folder.dir / "provenance.json", json.dumps(provenance, indent=2) + "\n")


def write_report(folder: RunFolder, rules: Rules, command: str) -> str:
    """Writes the figure and tables from the finished runs; returns the answer sentence."""
    frame = folder.load()
    labels = {arm: rules.label(arm) for arm in rules.arms}
    env = rules.env
    figure = learning_curves(
        frame,
        [Panel(f"{env}: {rules.algo.upper()}", env, list(rules.arms))],
        labels,
        folder.artifact("learning_curves.png"),
        per_seed=True,
    )
    baselines = {arm: "baseline" for arm in rules.arms if arm != "baseline"}
    # No threshold is known for a user's env: its two columns would say nothing.
    rows = summary(frame, [env], rules.arms, labels, {env: np.nan}, baselines)
    table = to_markdown(rows.drop(columns=["threshold", "steps to threshold"]))
    stats = exploration_stats(folder.load("log"), [env], rules.arms, labels)
    if not stats.empty:
        table += (
            f"\n\nWhat ESA did (training-log means, mean ± SE over seeds):\n\n{to_markdown(stats)}"
        )
    tables = judged(frame, rules)
    compact = compact_table(tables["first"], tables["whole"])
    verdicts = (
        to_markdown(compact) if not compact.empty else "(no comparison has two common seeds yet)"
    )
    sentence = answer(tables["first"], rules)
    verdicts += f"\n\n**Answer:** {sentence}\n"
    atomic_write_text(folder.artifact("summary.md"), table + "\n")
    atomic_write_text(folder.artifact("verdicts.md"), verdicts)
    seeds = (
        f"{min(rules.seeds)}-{max(rules.seeds)}" if len(rules.seeds) > 1 else str(rules.seeds[0])
    )
    page = (
        f"# Does ESA help on {env}? ({rules.algo.upper()})\n\n"
        f"Made by `{command}` (`esa-compare`; the rules are in `rules.json`, the versions "
        "and host in `provenance.json`).\n\n"
        f"- Arms: {', '.join(labels.values())}; settings: {rules.hyperparams.get('source')}.\n"
        f"- Seeds {seeds} for every arm; {rules.steps:,} steps per run; evaluation every "
        f"{rules.eval_every:,} steps, {rules.eval_episodes} deterministic episodes.\n"
        f"- Metric: {rules.metric}.\n- Decision: {rules.decision}.\n\n"
        f"![learning curves]({figure.name})\n\n{table}\n\n"
        "Verdicts (P(arm better) with its 95 % CI; two-sided Mann-Whitney p, Holm-corrected "
        f"within each metric):\n\n{verdicts}"
    )
    atomic_write_text(folder.artifact("RESULTS.md"), page)
    write_provenance(folder, rules, command, runs_digest(folder))
    return sentence
