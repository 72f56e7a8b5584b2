"""The Optuna loop behind ``python -m esa_experiments run default_search``.

Reproducible and resumable: the TPE sampler has a fixed seed, and on a resume the recorded
trials are asked again in order (so the sampler's random state advances exactly as in an
uninterrupted search) and told their recorded scores; every run is a normal run of the
study, skipped when already finished.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import pandas as pd
from rich.console import Console

from esa_experiments.execution import execute
from esa_experiments.runs import RunSpec, RunStore, atomic_write_text


class SearchStudy(Protocol):
    """What the loop needs of a study with a search space (``studies.default_search``).

    The study passes itself (its module) in, so the loop does not import any study.
    """

    NAME: str
    SPACE: dict[str, tuple[str, Any]]
    FINALISTS: int
    BUDGETS: Mapping[str, Any]

    def trial_spec(
        self, args: Any, budget: str, number: int, params: dict[str, Any], seed: int
    ) -> RunSpec:
        """The run of trial ``number`` on ``seed``."""
        ...

    def baseline_spec(self, args: Any, budget: str, seed: int) -> RunSpec:
        """The baseline run every trial is compared with, on ``seed``."""
        ...

    def trials_path(self, store: RunStore) -> Path:
        """Where the search's record of finished trials lives."""
        ...

    def load_trials(self, store: RunStore) -> list[dict[str, Any]]:
        """The finished trials, in order."""
        ...

    def scores(self, store: RunStore) -> pd.DataFrame:
        """The score (AUC) per (method, seed) of every finished run."""
        ...

    def esa_fields(self, params: dict[str, Any]) -> dict[str, Any]:
        """The EsaConfig fields of a trial's parameters."""
        ...


def _distributions(study: SearchStudy) -> dict[str, Any]:
    import optuna.distributions as d

    out: dict[str, Any] = {}
    for name, (kind, values) in study.SPACE.items():
        if kind == "log":
            low, high = values
            out[name] = d.FloatDistribution(low, high, log=True)
        elif kind == "uniform":
            out[name] = d.FloatDistribution(*values)
        else:
            out[name] = d.CategoricalDistribution(values)
    return out


def _run(
    specs: Sequence[RunSpec], store: RunStore, jobs: int, root: Path, console: Console
) -> None:
    pending = store.pending(specs)
    if pending:
        failed = [o for o in execute(pending, jobs, root, console) if o.error]
        if failed:
            raise RuntimeError(f"{len(failed)} run(s) failed, first:\n{failed[0].error}")


def _gains(study: SearchStudy, store: RunStore, method: str, seeds: Sequence[int]) -> np.ndarray:
    auc = study.scores(store)
    ppo = auc[auc.method == "ppo"].set_index("seed").auc
    mine = auc[auc.method == method].set_index("seed").auc
    return np.array([mine[s] - ppo[s] for s in seeds])


def search(
    study: SearchStudy,
    budget: str,
    seeds: Sequence[int],
    jobs: int,
    root: Path,
    console: Console,
) -> dict[str, Any]:
    """Runs (or resumes) the search and the finalists' confirmation; returns the winner."""
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    args = study.BUDGETS[budget]
    store = RunStore(study.NAME, budget, root)
    record = study.load_trials(store)
    _run([study.baseline_spec(args, budget, s) for s in seeds], store, jobs, root, console)

    sampler = optuna.samplers.TPESampler(seed=0, n_startup_trials=8)
    optimizer = optuna.create_study(direction="maximize", sampler=sampler)
    distributions = _distributions(study)
    for number in range(args.trials):
        trial = optimizer.ask(distributions)
        if number < len(record):
            if trial.params != record[number]["params"]:
                raise RuntimeError(
                    f"trial {number}: expected the recorded params {record[number]['params']}, "
                    f"got {trial.params}; the record belongs to another search"
                )
            optimizer.tell(trial, record[number]["score"])
            continue
        specs = [study.trial_spec(args, budget, number, trial.params, s) for s in seeds]
        _run(specs, store, jobs, root, console)
        score = float(_gains(study, store, f"trial{number:03d}", seeds).mean())
        optimizer.tell(trial, score)
        record.append(
            {"number": number, "params": trial.params, "seeds": list(seeds), "score": score}
        )
        atomic_write_text(study.trials_path(store), "".join(json.dumps(r) + "\n" for r in record))
        console.print(f"trial {number}: AUC gain over PPO {score:+.1f} with {trial.params}")
    return _confirm(study, args, budget, record, seeds, store, jobs, root, console)


def _confirm(
    study: SearchStudy,
    args: Any,
    budget: str,
    record: list[dict[str, Any]],
    seeds: Sequence[int],
    store: RunStore,
    jobs: int,
    root: Path,
    console: Console,
) -> dict[str, Any]:
    extra = list(range(max(seeds) + 1, max(seeds) + 1 + args.confirmation_seeds))
    finalists = sorted(record, key=lambda r: r["score"], reverse=True)[: study.FINALISTS]
    specs = [study.baseline_spec(args, budget, s) for s in extra]
    for trial in finalists:
        specs += [
            study.trial_spec(args, budget, trial["number"], trial["params"], s) for s in extra
        ]
    _run(specs, store, jobs, root, console)
    results = []
    for trial in finalists:
        gains = _gains(study, store, f"trial{trial['number']:03d}", [*seeds, *extra])
        results.append({**trial, "seeds": [*seeds, *extra], "confirmed": float(gains.mean())})
    winner = max(results, key=lambda r: r["confirmed"])
    summary = {
        "finalists": results,
        "winner": winner,
        "esa_fields": study.esa_fields(winner["params"]),
    }
    atomic_write_text(store.artifact("winner.json"), json.dumps(summary, indent=2) + "\n")
    console.print(
        f"winner: trial {winner['number']} ({winner['confirmed']:+.1f}) {summary['esa_fields']}"
    )
    return summary
