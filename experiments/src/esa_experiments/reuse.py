"""Runs a study reads from another study's committed results instead of running them again.

A study may name, per arm and env, the study whose finished runs have exactly the
configuration it would run: the same env, stored arm name, seed and resolved configuration,
that is the same fingerprint (:meth:`RunSpec.fingerprint` leaves the study out). Such a run is
read from there and not run again; a run the source lacks, or holds with another
configuration, is planned and run in the study itself. The sources are the committed results
beside the code (``experiments/results``), read the way E2 reads E1's picks.

Equal fingerprints mean equal settings, not equal code: a reused run comes from the code of
its own study's commit (that study's ``PROVENANCE.md``), and :func:`rerun_table` measures
how far a run made here departs from the committed run of the same settings.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
from esa_client.compare.tables import per_seed

from esa_experiments.runs import EXPERIMENTS_DIR, RunSpec, RunStore


@dataclass(frozen=True)
class Reuse:
    """Where a study's reused runs come from.

    Attributes:
        sources: arm -> env -> the study whose runs of that arm on that env are read.
        base: the folder holding ``results/`` (default: ``experiments/``).
        enabled: False reads nothing (the smoke budgets: nothing committed to read).
    """

    sources: Mapping[str, Mapping[str, str]] = field(default_factory=dict)
    base: Path = EXPERIMENTS_DIR
    enabled: bool = True

    def source(self, spec: RunSpec) -> RunStore | None:
        """The store holding a finished run with ``spec``'s fingerprint, or None (run it)."""
        study = self.sources.get(spec.method, {}).get(spec.env)
        if not self.enabled or study is None:
            return None
        store = RunStore(study, spec.budget, self.base)
        return store if store.status(spec) == "done" else None


def to_run(planned: Sequence[RunSpec], reuse: Reuse) -> list[RunSpec]:
    """The planned runs no source holds, in order: what the study runs itself."""
    return [spec for spec in planned if reuse.source(spec) is None]


def _read(path: Path, spec: RunSpec) -> pd.DataFrame:
    frame = pd.read_csv(path)
    frame.insert(0, "seed", spec.seed)
    frame.insert(0, "method", spec.method)
    frame.insert(0, "env", spec.env)
    return frame


def load_runs(
    store: RunStore, planned: Sequence[RunSpec], reuse: Reuse, table: str | None = None
) -> pd.DataFrame:
    """The study's own finished runs and the reused ones, as :meth:`RunStore.load` gives them.

    A run the study holds itself is never read from a source as well.

    Args:
        store: the study's results.
        planned: every run of the study, reused or not.
        reuse: where the reused runs come from.
        table: an extra table's key (``log``) instead of the main CSVs.

    Raises:
        FileNotFoundError: when there is no run at all.
    """
    frames = []
    own: set[tuple[str, str, int]] = set()
    try:
        mine = store.load(table)
        frames.append(mine)
        own = set(zip(mine.env, mine.method, mine.seed.astype(int), strict=True))
    except FileNotFoundError:
        pass
    for spec in planned:
        source = reuse.source(spec)
        if source is None or (spec.env, spec.method, spec.seed) in own:
            continue
        path = source.csv_path(spec) if table is None else source.table_path(spec, table)
        if path.is_file():
            frames.append(_read(path, spec))
    if not frames:
        raise FileNotFoundError(
            f"expected finished runs in {store.runs_dir} or its sources, found none: "
            "run the study first"
        )
    return pd.concat(frames, ignore_index=True)


def _seeds(seeds: Sequence[int]) -> str:
    """``[0, 1, 2, 4]`` as ``0-2, 4``."""
    parts: list[list[int]] = []
    for seed in sorted(seeds):
        if parts and seed == parts[-1][-1] + 1:
            parts[-1].append(seed)
        else:
            parts.append([seed])
    return ", ".join(f"{p[0]}-{p[-1]}" if len(p) > 2 else ", ".join(map(str, p)) for p in parts)


def provenance_table(
    store: RunStore, planned: Sequence[RunSpec], reuse: Reuse, labels: Mapping[str, str]
) -> pd.DataFrame:
    """Per arm and group of envs alike: the seeds read from another study, run here, to run."""
    where_of: dict[tuple[str, str], dict[str, list[int]]] = {}
    for spec in planned:
        source = reuse.source(spec)
        if source is not None:
            where = f"read from `{source.study}`"
        elif store.status(spec) == "done":
            where = "run here"
        else:
            where = "not run yet"
        where_of.setdefault((spec.method, spec.env), {}).setdefault(where, []).append(spec.seed)
    arms = list(dict.fromkeys(spec.method for spec in planned))  # the study's order
    columns = sorted({where for parts in where_of.values() for where in parts})
    groups: dict[tuple[str, tuple[str, ...]], list[str]] = {}
    for (arm, env), parts in where_of.items():
        cells = tuple(_seeds(parts.get(where, [])) for where in columns)
        groups.setdefault((arm, cells), []).append(env)
    return pd.DataFrame(
        [
            {
                "arm": labels.get(arm, arm),
                "envs": ", ".join(envs),
                **dict(zip(columns, cells, strict=True)),
            }
            for (arm, cells), envs in sorted(groups.items(), key=lambda g: arms.index(g[0][0]))
        ]
    )


def rerun_table(
    frame: pd.DataFrame,
    specs: Sequence[RunSpec],
    against: Mapping[str, Mapping[str, str]],
    base: Path,
    early: float,
    labels: Mapping[str, str],
) -> pd.DataFrame:
    """Runs made here against another study's committed runs of the same settings.

    Per (env, arm) of ``against``: on the seeds both have (the same fingerprint), how many
    evaluation curves are identical, where the others first depart, and the mean AUC over
    the first ``early`` of the budget and over the whole curve, here and committed.

    Args:
        frame: this study's runs (:func:`load_runs`).
        specs: this study's runs of those arms.
        against: arm -> env -> the study holding the committed runs.
        base: the folder holding ``results/``.
        early: the fraction of the budget of the primary metric (E2's: 1/3).
        labels: arm -> display name.
    """
    rows = []
    by_pair: dict[tuple[str, str], list[RunSpec]] = {}
    for spec in specs:
        if spec.env in against.get(spec.method, {}):
            by_pair.setdefault((spec.env, spec.method), []).append(spec)
    for (env, arm), pair_specs in by_pair.items():
        other = RunStore(against[arm][env], pair_specs[0].budget, base)
        here_runs, there_runs, departs = [], [], []
        for spec in pair_specs:
            here = frame[(frame.env == env) & (frame.method == arm) & (frame.seed == spec.seed)]
            if here.empty or other.status(spec) != "done":
                continue
            there = _read(other.csv_path(spec), spec)
            a = here.sort_values("step")[["step", "return_mean"]].to_numpy(float)
            b = there.sort_values("step")[["step", "return_mean"]].to_numpy(float)
            n = min(len(a), len(b))
            differ = np.flatnonzero((a[:n] != b[:n]).any(axis=1))
            if len(differ) or len(a) != len(b):
                # Bit for bit: the first evaluation whose step or return is not the same.
                departs.append(int(a[differ[0] if len(differ) else n - 1, 0]))
            here_runs.append(here)
            there_runs.append(there)
        if not here_runs:
            continue
        total = float(pair_specs[0].config["total_steps"])
        row = {
            "env": env,
            "arm": labels.get(arm, arm),
            "committed in": f"`{other.study}`",
            "seeds": len(here_runs),
            "identical curves": f"{len(here_runs) - len(departs)} of {len(here_runs)}",
            "first departure (step)": ", ".join(map(str, departs)) or "-",
        }
        for name, cut in (("first third", early * total), ("whole", total)):
            means = [
                per_seed(pd.concat(runs)[pd.concat(runs).step <= cut], np.nan).auc.mean()
                for runs in (here_runs, there_runs)
            ]
            row[f"mean AUC, {name}: here / committed"] = f"{means[0]:.1f} / {means[1]:.1f}"
        rows.append(row)
    return pd.DataFrame(rows)
