"""Re-runs the first steps of committed runs from this checkout and compares them bit for bit.

A committed run's sidecar holds its whole configuration. This script trains the same run
for its first ``--steps`` steps (the budget cut, nothing else changed) in this checkout and
compares every evaluation (step and mean return) with the committed CSV, bit for bit: the
cheap way to say whether main re-runs a study's runs, and where it departs. Nothing is
written under ``results/``.

A prefix is the run's own prefix only when nothing depends on the budget, so the script
refuses an ESA run that fades (its strength is a fraction of the budget) and a learning
rate or clip range given as a schedule.

Usage::

    python experiments/scripts/rerun_prefix.py confirmation Hopper-v5__sac_esa__s0 --steps 5000
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass

import pandas as pd
import torch as th
import tyro
from tyro.conf import Positional

from esa_experiments.runs import RunSpec, RunStore
from esa_experiments.training import trained


@dataclass(frozen=True)
class Args:
    """Which committed run, and how much of it."""

    study: Positional[str]
    """The study whose committed run (``results/<study>/runs``) is re-run."""
    run: Positional[str]
    """The run's file stem, ``<env>__<arm>__s<seed>``."""
    steps: int = 6_144
    """The prefix: a multiple of the run's evaluation interval."""


def prefix_spec(store: RunStore, run: str, steps: int) -> RunSpec:
    """The committed run's spec with its budget cut to ``steps``.

    Raises:
        ValueError: For a run whose training depends on its budget, or a prefix that is not
            a whole number of evaluation intervals.
    """
    meta = json.loads((store.runs_dir / f"{run}.json").read_text())
    config = meta["config"]
    esa = config["hyperparams"].get("esa") or {}
    if esa.get("fade") is not None:
        raise ValueError(f"expected a run without fade, got fade={esa['fade']}: no prefix")
    for key in ("learning_rate", "clip_range"):
        if isinstance(config["hyperparams"].get(key), str):
            raise ValueError(f"expected a constant {key}, got a schedule: no prefix")
    if steps % config["eval_every"] or steps > config["total_steps"]:
        raise ValueError(
            f"expected a multiple of {config['eval_every']} up to {config['total_steps']}, "
            f"got {steps}"
        )
    return RunSpec(
        meta["study"],
        meta["env"],
        meta["method"],
        meta["seed"],
        meta["budget"],
        {**config, "total_steps": steps},
    )


def compare(committed: pd.DataFrame, rerun: pd.DataFrame, steps: int) -> pd.DataFrame:
    """Both runs' evaluations up to ``steps``, side by side, and whether each is identical.

    The re-run goes through the CSV writer and reader as the committed run did, so that
    equal runs compare equal bit for bit.
    """
    columns = ["step", "return_mean"]
    rerun = pd.read_csv(io.StringIO(rerun[columns].to_csv(index=False)))
    both = committed[committed.step <= steps][columns].merge(
        rerun, on="step", how="outer", suffixes=(" committed", " rerun")
    )
    both["difference"] = both["return_mean rerun"] - both["return_mean committed"]
    both["identical"] = both["return_mean committed"] == both["return_mean rerun"]
    return both


def main() -> None:
    """Re-runs the prefix and prints the comparison."""
    args = tyro.cli(Args)
    th.set_num_threads(1)  # as the studies' workers run
    store = RunStore(args.study, "full")
    spec = prefix_spec(store, args.run, args.steps)
    with trained(spec, lambda _: None) as (result, _):
        rerun = result.frame
    table = compare(pd.read_csv(store.runs_dir / f"{args.run}.csv"), rerun, args.steps)
    print(table.to_string(index=False))
    differ = table[~table.identical]
    verdict = (
        f"identical through step {args.steps}"
        if differ.empty
        else f"departs at step {int(differ.step.iloc[0])}"
    )
    print(f"{args.study} {args.run}: {verdict}")


if __name__ == "__main__":
    main()
