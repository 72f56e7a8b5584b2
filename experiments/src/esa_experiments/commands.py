"""The commands of ``python -m esa_experiments``: run studies, plot them, list them.

Examples::

    python -m esa_experiments list
    python -m esa_experiments run example1 --budget full
    python -m esa_experiments run mujoco --budget full --seeds 0-4 --jobs 2
    python -m esa_experiments run mujoco --budget smoke --methods ppo ppo_esa --envs Hopper-v5
    python -m esa_experiments plot mujoco --budget full
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from rich.console import Console

from esa_experiments.runs import BUDGETS, EXPERIMENTS_DIR, RunStore, parse_seeds
from esa_experiments.studies import STUDY_NAMES, Study, load_study


class CliError(Exception):
    """Bad command-line input; reported as ``error: ...`` with exit code 2."""


def _selection(kind: str, given: Sequence[str] | None, allowed: Sequence[str]) -> tuple[str, ...]:
    if not given:
        return tuple(allowed)
    names = [name for item in given for name in item.split(",") if name]
    unknown = [name for name in names if name not in allowed]
    if unknown:
        raise CliError(f"unknown {kind} {unknown}; expected some of {list(allowed)}")
    return tuple(dict.fromkeys(names))


def _study(name: str) -> Study:
    try:
        return load_study(name)
    except ValueError as err:
        raise CliError(str(err)) from None


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m esa_experiments", description="ESA reproduction suite."
    )
    parser.add_argument(
        "--root",
        type=Path,
        default=EXPERIMENTS_DIR,
        help="folder holding results/, results-smoke/ and RESULTS.md (default: experiments/)",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("list", help="list the studies, their envs, methods and finished runs")
    run = sub.add_parser("run", help="run a study (finished runs are skipped)")
    plot = sub.add_parser("plot", help="write a study's figures and tables, update RESULTS.md")
    for command in (run, plot):
        command.add_argument("study", help=f"one of {', '.join(STUDY_NAMES)}")
        command.add_argument("--budget", default="smoke", help=f"one of {', '.join(BUDGETS)}")
    run.add_argument("--seeds", help="e.g. 0-4, 3 or 0,2,5-7 (default: the study's)")
    run.add_argument("--jobs", type=int, default=1, help="parallel worker processes")
    run.add_argument("--methods", nargs="+", help="subset of the study's methods")
    run.add_argument("--envs", nargs="+", help="subset of the study's envs")
    run.add_argument("--dry-run", action="store_true", help="only show what would run")
    return parser


def _list(root: Path, console: Console) -> None:
    for name in STUDY_NAMES:
        study = load_study(name)
        console.print(f"[bold]{name}[/]: {study.DESCRIPTION}")
        console.print(f"  envs:    {', '.join(study.ENVS)}")
        console.print(f"  methods: {', '.join(study.METHODS)}")
        console.print(f"  default seeds: {study.DEFAULT_SEEDS}")
        for budget in BUDGETS:
            runs = RunStore(name, budget, root).runs_dir
            finished = len(list(runs.glob("*.json"))) if runs.is_dir() else 0
            console.print(f"  {budget}: {finished} finished run(s) in {runs}")


def _run(options: argparse.Namespace, console: Console) -> int:
    from esa_experiments.execution import execute

    study = _study(options.study)
    try:
        seeds = parse_seeds(options.seeds or study.DEFAULT_SEEDS)
    except ValueError as err:
        raise CliError(f"--seeds: {err}") from None
    if options.jobs < 1:
        raise CliError(f"--jobs: expected an integer >= 1, got {options.jobs}")
    drive = getattr(study, "drive", None)
    if drive is not None:
        # A study that decides its runs as it goes (a search); it is resumable itself.
        drive(options.budget, seeds, options.jobs, options.root, console)
        console.print(
            f"Next: python -m esa_experiments plot {study.NAME} --budget {options.budget}"
        )
        return 0
    envs = _selection("envs", options.envs, study.ENVS)
    methods = _selection("methods", options.methods, study.METHODS)
    specs = study.specs(study.BUDGETS[options.budget], options.budget, seeds, envs, methods)
    store = RunStore(study.NAME, options.budget, options.root)
    statuses = [store.status(spec) for spec in specs]
    pending = [spec for spec, status in zip(specs, statuses, strict=True) if status != "done"]
    console.print(
        f"{study.NAME} ({options.budget}): {len(specs)} runs, {statuses.count('done')} done, "
        f"{statuses.count('stale')} stale (config changed: rerun), "
        f"{statuses.count('todo')} to do -> {store.runs_dir}"
    )
    if options.dry_run or not pending:
        for spec in pending:
            console.print(f"  would run {spec.label} ({spec.config['total_steps']} steps)")
        return 0
    outcomes = execute(pending, options.jobs, options.root, console)
    failed = [o for o in outcomes if o.error]
    for outcome in failed:
        console.print(f"[red]FAILED[/] {outcome.spec.label}\n{outcome.error}")
    console.print(
        f"{len(outcomes) - len(failed)} run(s) finished, {len(failed)} failed. "
        f"Next: python -m esa_experiments plot {study.NAME} --budget {options.budget}"
    )
    return 1 if failed else 0


def _plot(options: argparse.Namespace, console: Console) -> int:
    from esa_experiments.reporting import update_results

    study = _study(options.study)
    store = RunStore(study.NAME, options.budget, options.root)
    try:
        section = study.report(store, study.BUDGETS[options.budget])
    except FileNotFoundError as err:
        raise CliError(str(err)) from None
    target = update_results(study.NAME, section, store)
    console.print(f"wrote {store.dir} and {target}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    parser = _parser()
    options = parser.parse_args(argv)
    console = Console()
    try:
        if getattr(options, "budget", BUDGETS[0]) not in BUDGETS:
            raise CliError(f"--budget: expected one of {list(BUDGETS)}, got {options.budget!r}")
        if options.command == "list":
            _list(options.root, console)
            return 0
        return _run(options, console) if options.command == "run" else _plot(options, console)
    except CliError as err:
        console.print(f"[red]error:[/] {err}", highlight=False)
        return 2


if __name__ == "__main__":
    sys.exit(main())
