"""The search that picked the shipped ``EsaConfig()`` default: InvertedPendulum-v5 only.

An Optuna TPE search (sampler seed 0, so the same history gives the same proposals) over
the section 1b law's knobs, each trial scored by PPO+ESA's AUC on the tuning seeds minus
plain PPO's on the same seeds. The tuning seeds (100, 101, ...) are not the campaign's
(0-9), so the campaign measures the chosen default on runs it was not selected on. The
best ``FINALISTS`` trials are then re-run on ``confirmation_seeds`` more seeds and the
best mean over all its seeds wins (a guard against picking a lucky trial).

What is searched (``SPACE``), in the units ESAPPO gives ESA (Box scaled to [-1, 1]; the
step and the trust region in units of the policy's standard deviation): the probe
amplitude K, the frequency as a fraction of the env's Nyquist frequency, the learning
rate, the trust region kappa, the leak lambda and the gate. Fixed: the normalized and
paired response and the policy's std as the action scale (what the audit found to work
at every Q scale), and everything PPO does (``configs/algorithms.toml``).

``python -m esa_experiments run default_search --budget full --jobs 2`` runs or resumes it
(every run is a normal, resumable run of this study; the trials are kept in
``results/default_search/trials.jsonl``, the finalists and the winner in ``winner.json``);
``python -m esa_experiments plot default_search --budget full`` writes the table and figure.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from matplotlib.figure import Figure
from rich.console import Console

from esa_experiments.runs import RunSpec, RunStore, atomic_write_text
from esa_experiments.studies import campaign
from esa_experiments.tables import per_seed, to_markdown
from esa_experiments.training import StepBudget, rl_spec, run_training

NAME = "default_search"
DESCRIPTION = "Optuna search for the shipped ESA default on InvertedPendulum-v5 (tuning seeds)"
ENV = "InvertedPendulum-v5"
ENVS = (ENV,)
METHODS = ("ppo", "ppo_esa")
DEFAULT_SEEDS = "100-102"
FINALISTS = 3

SPACE: dict[str, tuple[str, Any]] = {
    "amplitude": ("log", (0.05, 0.5)),
    "nyquist_fraction": ("uniform", (0.1, 0.9)),
    "learning_rate": ("log", (0.005, 0.2)),
    "trust_region": ("log", (0.05, 1.0)),
    "shift_leak": ("log", (0.001, 0.1)),
    "gate": ("categorical", ("none", 0.0, 0.05, 0.1, 0.2)),
}
"""EsaConfig field -> (distribution, range or choices); ``"none"`` is ``gate=None``."""


@dataclass(frozen=True)
class Args:
    """Arguments of the search.

    Attributes:
        budget: the step budget of every run (the campaign's InvertedPendulum budget).
        trials: Optuna trials.
        confirmation_seeds: further seeds for each finalist.
    """

    budget: StepBudget = field(default_factory=lambda: campaign.BUDGETS["full"].budgets[ENV])
    trials: int = 24
    confirmation_seeds: int = 5


BUDGETS = {
    "smoke": Args(campaign.SMOKE, trials=2, confirmation_seeds=1),
    "full": Args(),
}


def esa_fields(params: dict[str, Any]) -> dict[str, Any]:
    """The EsaConfig fields of a trial's parameters."""
    return {key: (None if value == "none" else value) for key, value in params.items()}


def trial_spec(args: Args, budget: str, number: int, params: dict[str, Any], seed: int) -> RunSpec:
    """The run of trial ``number`` on ``seed`` (stored as method ``trial<number>``)."""
    return rl_spec(
        NAME,
        ENV,
        "ppo_esa",
        seed,
        budget,
        args.budget,
        variant=f"trial{number:03d}",
        esa_overrides=esa_fields(params),
    )


def baseline_spec(args: Args, budget: str, seed: int) -> RunSpec:
    """Plain PPO on ``seed``: what every trial is compared with."""
    return rl_spec(NAME, ENV, "ppo", seed, budget, args.budget)


def trials_path(store: RunStore) -> Path:
    """The search's record: one JSON line per finished trial (number, params, seeds, score)."""
    return store.artifact("trials.jsonl")


def load_trials(store: RunStore) -> list[dict[str, Any]]:
    """The finished trials, in order."""
    path = trials_path(store)
    if not path.is_file():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def specs(
    args: Args,
    budget: str,
    seeds: list[int],
    envs: tuple[str, ...],
    methods: tuple[str, ...],
    base: Path | None = None,
) -> list[RunSpec]:
    """The plain-PPO runs of ``seeds`` and every recorded trial's runs (under ``base``)."""
    out = [baseline_spec(args, budget, seed) for seed in seeds]
    for trial in load_trials(RunStore(NAME, budget, base)):
        out += [
            trial_spec(args, budget, trial["number"], trial["params"], s) for s in trial["seeds"]
        ]
    return out


def drive(budget: str, seeds: list[int], jobs: int, root: Path, console: Console) -> None:
    """Runs or resumes the search (what ``run default_search`` does)."""
    import sys

    from esa_experiments.search import search

    search(sys.modules[__name__], budget, seeds, jobs, root, console)


run = run_training
"""One run: train with periodic evaluation, nothing else."""


def scores(store: RunStore) -> pd.DataFrame:
    """AUC per (method, seed) of every finished run."""
    frame = store.load()
    rows = [
        {"method": method, "seed": seed, "auc": per_seed(runs, np.nan).auc.iloc[0]}
        for (method, seed), runs in frame.groupby(["method", "seed"])
    ]
    return pd.DataFrame(rows)


def report(store: RunStore, args: Args) -> str:
    """The trials ranked by their AUC gain over PPO, and the objective over the search."""
    trials = load_trials(store)
    if not trials:
        raise FileNotFoundError(f"expected trials in {trials_path(store)}: run the search first")
    auc = scores(store)
    ppo = auc[auc.method == "ppo"].set_index("seed").auc
    rows = []
    for trial in trials:
        mine = auc[auc.method == f"trial{trial['number']:03d}"].set_index("seed").auc
        gain = (mine - ppo.reindex(mine.index)).dropna()
        spread = gain.sem() if len(gain) > 1 else 0.0
        rows.append(
            {
                "trial": trial["number"],
                "seeds": len(gain),
                "AUC gain over PPO": f"{gain.mean():+.1f} ± {spread:.1f}",
                "gain": gain.mean(),
                **{key: _short(value) for key, value in trial["params"].items()},
            }
        )
    table = pd.DataFrame(rows).sort_values("gain", ascending=False)
    figure = _figure(table, store.artifact("search.png"))
    text = to_markdown(table.drop(columns="gain"))
    atomic_write_text(store.artifact("table.md"), text + "\n")
    return (
        f"![default search]({store.relative(figure)})\n\nTrials ranked by mean AUC gain over "
        f"plain PPO on the same seeds (± SE over seeds):\n\n{text}\n"
    )


def _short(value: Any) -> str:
    return f"{value:.3g}" if isinstance(value, float) else str(value)


def _figure(table: pd.DataFrame, path: Path) -> Path:
    fig = Figure(figsize=(6, 3.5), layout="constrained")
    ax = fig.subplots()
    ordered = table.sort_values("trial")
    ax.plot(ordered.trial, ordered.gain, "o", label="trial")
    ax.plot(ordered.trial, ordered.gain.cummax(), "-", label="best so far")
    ax.axhline(0.0, color="grey", linewidth=0.8)
    ax.set_xlabel("trial")
    ax.set_ylabel("AUC gain over PPO (mean over seeds)")
    ax.set_title(f"ESA default search on {ENV}")
    ax.legend(fontsize=8)
    fig.savefig(path, dpi=120)
    return path
