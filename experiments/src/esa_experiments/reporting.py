"""Study reports: the RL figure + table of a study, and the generated parts of RESULTS.md.

``RESULTS.md`` is hand-written prose with generated sections between
``<!-- BEGIN <study> -->`` and ``<!-- END <study> -->`` markers; ``plot STUDY``
replaces only its own section (and appends it if the markers are missing), so
the discussion around it survives regeneration. Smoke results never touch
``RESULTS.md``: their section goes to ``results-smoke/<study>/section.md``.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from pathlib import Path

import pandas as pd
from esa_client.compare.plotting import Panel, learning_curves
from esa_client.compare.tables import exploration_stats, summary, to_markdown

from esa_experiments.algorithms import BASELINE_OF, LABELS
from esa_experiments.runs import RunStore, atomic_write_text
from esa_experiments.tasks import TASKS
from esa_experiments.training import StepBudget


def budget_table(budgets: Mapping[str, StepBudget]) -> str:
    """Markdown table of a study's per-env step budgets."""
    lines = [
        "| env | PPO-family steps | SAC/DDPG steps | eval every (on/off) | eval episodes |",
        "|---|---|---|---|---|",
    ]
    for env, b in budgets.items():
        # A family the study does not train has no evaluation interval to show.
        on, off = (
            f"{interval:,}" if steps else "-"
            for steps, interval in (
                (b.on_policy, b.eval_every_on),
                (b.off_policy, b.eval_every_off),
            )
        )
        lines.append(
            f"| {env} | {b.on_policy:,} | {b.off_policy:,} | {on} / {off} | {b.eval_episodes} |"
        )
    return "\n".join(lines)


def rl_section(
    store: RunStore,
    panels: Sequence[Panel],
    envs: Sequence[str],
    methods: Sequence[str],
    *,
    labels: Mapping[str, str] | None = None,
    baselines: Mapping[str, str] | None = None,
    figure_name: str = "learning_curves.png",
    suptitle: str = "",
    ncols: int = 2,
    per_seed: bool = False,
    frame: pd.DataFrame | None = None,
    log: pd.DataFrame | None = None,
    inline: bool = True,
) -> str:
    """Writes a study's learning-curve PNG and summary table; returns its Markdown.

    Args:
        store: the study's results.
        panels: subplots of the figure.
        envs: envs of the table, in order.
        methods: methods of the table, in order.
        labels: method -> display name (default: the method registry's labels).
        baselines: method -> method its overhead is measured against.
        figure_name: PNG file name in the study folder.
        suptitle: figure title.
        ncols: subplots per row.
        per_seed: also draw every seed's curve (thin lines).
        frame: the runs to report (default: the store's; a study that reads another
            study's runs passes them all).
        log: their training logs (default: the store's).
        inline: put the tables in the returned Markdown; else link ``table.md``, which
            holds them either way (keeps RESULTS.md short for studies with many arms).
    """
    labels = {**LABELS, **(labels or {})}
    frame = store.load() if frame is None else frame
    figure = learning_curves(
        frame,
        panels,
        labels,
        store.artifact(figure_name),
        suptitle=suptitle,
        ncols=ncols,
        per_seed=per_seed,
    )
    thresholds = {env: TASKS[env].threshold for env in envs}
    table = to_markdown(summary(frame, envs, methods, labels, thresholds, baselines or BASELINE_OF))
    stats = exploration_stats(store.load("log") if log is None else log, envs, methods, labels)
    if not stats.empty:
        table += (
            "\n\nWhat the exploration add-ons did (training-log means, mean ± SE over seeds):"
            f"\n\n{to_markdown(stats)}"
        )
    path = store.artifact("table.md")
    atomic_write_text(path, table + "\n")
    if not inline:
        table = (
            f"Per arm and env (final return, AUC, steps to threshold, training time, what ESA "
            f"did): [{path.name}]({store.relative(path)})."
        )
    return f"![{store.study}]({store.relative(figure)})\n\n{table}\n"


def verdicts_markdown(table: pd.DataFrame) -> str:
    """A verdict table as Markdown, or a sentence saying there is none yet."""
    return to_markdown(table) if not table.empty else "(no comparison has two seeds yet)"


def write_verdicts(store: RunStore, primary: pd.DataFrame, whole: pd.DataFrame) -> tuple[str, str]:
    """Writes a study's full verdict tables and returns their Markdown.

    The files are ``verdicts_first.md`` (the primary metric, the first third of the budget)
    and ``verdicts_whole.md``; ``client-py/examples/demo.py`` reads them by these names.
    """
    first, overall = verdicts_markdown(primary), verdicts_markdown(whole)
    for name, markdown in (("first", first), ("whole", overall)):
        atomic_write_text(store.artifact(f"verdicts_{name}.md"), markdown + "\n")
    return first, overall


def update_results(study: str, section: str, store: RunStore) -> Path:
    """Puts a study's generated section into RESULTS.md (full budget) or next to its results."""
    if store.budget != "full":
        target = store.artifact("section.md")
        atomic_write_text(target, section)
        return target
    path = store.base / "RESULTS.md"
    begin, end = f"<!-- BEGIN {study} -->", f"<!-- END {study} -->"
    note = f"<!-- generated by `python -m esa_experiments plot {study} --budget full` -->"
    block = f"{begin}\n{note}\n{section.strip()}\n{end}"
    text = path.read_text() if path.is_file() else "# Results\n"
    pattern = re.compile(re.escape(begin) + r".*?" + re.escape(end), re.DOTALL)
    if pattern.search(text):
        text = pattern.sub(lambda _: block, text)
    else:
        text = text.rstrip("\n") + f"\n\n## {study}\n\n{block}\n"
    atomic_write_text(path, text if text.endswith("\n") else text + "\n")
    return path
