"""The commands of ``python -m esa_experiments``: run studies, plot them, list them.

Examples::

    python -m esa_experiments list
    python -m esa_experiments run example1 --budget full
    python -m esa_experiments run paper_figures --budget full --seeds 0-4 --jobs 2
    python -m esa_experiments run paper_figures --methods ppo ppo_esa --envs Hopper-v5
    python -m esa_experiments plot paper_figures --budget full
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import tyro
from rich.console import Console
from tyro.conf import Positional, arg, subcommand

from esa_experiments.runs import BUDGETS, EXPERIMENTS_DIR, RunStore, parse_seeds
from esa_experiments.studies import STUDY_NAMES, Study, StudyJob, load_study


class CliError(Exception):
    """Bad command-line input; reported as ``error: ...`` with exit code 2."""


@dataclass(frozen=True)
class ListStudies:
    """List the studies, their envs, methods and finished runs."""


@dataclass(frozen=True)
class _StudyCommand:
    # Plain strs rather than Literals: main() checks them, so that the error names what is
    # known the way the rest of the suite does, and main() returns its exit code.
    study: Annotated[Positional[str], arg(metavar="STUDY", help=f"one of {', '.join(STUDY_NAMES)}")]
    budget: Annotated[str, arg(help=f"one of {', '.join(BUDGETS)}")] = "smoke"


@dataclass(frozen=True)
class Run(_StudyCommand):
    """Run a study (finished runs are skipped)."""

    seeds: Annotated[
        str | None, arg(metavar="SEEDS", help_behavior_hint="(default: the study's)")
    ] = None
    """E.g. 0-4, 3 or 0,2,5-7."""
    jobs: int = 1
    """Parallel worker processes."""
    methods: Annotated[tuple[str, ...], arg(help_behavior_hint="(default: all)")] = ()
    """Subset of the study's methods (space- or comma-separated)."""
    envs: Annotated[tuple[str, ...], arg(help_behavior_hint="(default: all)")] = ()
    """Subset of the study's envs (space- or comma-separated)."""
    dry_run: bool = False
    """Only show what would run."""


@dataclass(frozen=True)
class Plot(_StudyCommand):
    """Write a study's figures and tables, update RESULTS.md."""


@dataclass(frozen=True)
class Cli:
    """ESA reproduction suite."""

    command: (
        Annotated[ListStudies, subcommand("list", prefix_name=False)]
        | Annotated[Run, subcommand("run", prefix_name=False)]
        | Annotated[Plot, subcommand("plot", prefix_name=False)]
    )
    root: Path = EXPERIMENTS_DIR
    """Folder holding results/, results-smoke/ and RESULTS.md."""


def parse(argv: Sequence[str] | None = None) -> Cli:
    """Parses ``argv`` (default: ``sys.argv[1:]``); malformed input exits with code 2."""
    return tyro.cli(
        Cli,
        args=argv,
        prog="python -m esa_experiments",
        config=(tyro.conf.OmitArgPrefixes, tyro.conf.FlagCreatePairsOff),
    )


def _selection(kind: str, given: Sequence[str], allowed: Sequence[str]) -> tuple[str, ...]:
    if not given:
        return tuple(allowed)
    names = [name for item in given for name in item.split(",") if name]
    unknown = [name for name in names if name not in allowed]
    if unknown:
        raise CliError(f"unknown {kind} {unknown}; expected some of {list(allowed)}")
    return tuple(dict.fromkeys(names))


def _study(command: _StudyCommand) -> Study:
    if command.budget not in BUDGETS:
        raise CliError(f"--budget: expected one of {list(BUDGETS)}, got {command.budget!r}")
    try:
        return load_study(command.study)
    except ValueError as err:
        raise CliError(str(err)) from None


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


def _run(options: Run, root: Path, console: Console) -> int:
    from esa_client.compare.execution import execute

    study = _study(options)
    try:
        seeds = parse_seeds(options.seeds or study.DEFAULT_SEEDS)
    except ValueError as err:
        raise CliError(f"--seeds: {err}") from None
    if options.jobs < 1:
        raise CliError(f"--jobs: expected an integer >= 1, got {options.jobs}")
    envs = _selection("envs", options.envs, study.ENVS)
    methods = _selection("methods", options.methods, study.METHODS)
    specs = study.specs(study.BUDGETS[options.budget], options.budget, seeds, envs, methods)
    store = RunStore(study.NAME, options.budget, root)
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
    outcomes = execute(pending, options.jobs, StudyJob(root, (study.NAME,)), console)
    failed = [o for o in outcomes if o.error]
    for outcome in failed:
        console.print(f"[red]FAILED[/] {outcome.spec.label}\n{outcome.error}")
    skipped = sum(o.skipped for o in outcomes)
    console.print(
        f"{len(outcomes) - len(failed) - skipped} run(s) finished, {len(failed)} failed, "
        f"{skipped} done meanwhile by another runner. "
        f"Next: python -m esa_experiments plot {study.NAME} --budget {options.budget}"
    )
    return 1 if failed else 0


def _plot(options: Plot, root: Path, console: Console) -> int:
    from esa_experiments.reporting import update_results

    study = _study(options)
    store = RunStore(study.NAME, options.budget, root)
    try:
        section = study.report(store, study.BUDGETS[options.budget])
    except FileNotFoundError as err:
        raise CliError(str(err)) from None
    target = update_results(study.NAME, section, store)
    console.print(f"wrote {store.dir} and {target}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    cli = parse(argv)
    console = Console()
    try:
        if isinstance(cli.command, Run):
            return _run(cli.command, cli.root, console)
        if isinstance(cli.command, Plot):
            return _plot(cli.command, cli.root, console)
        _list(cli.root, console)
        return 0
    except CliError as err:
        console.print(f"[red]error:[/] {err}", highlight=False)
        return 2
    except KeyboardInterrupt:
        # Ctrl-C or SIGTERM, after the runner stopped its workers: a way back, no traceback.
        resume = " Finished runs are kept: the same command resumes."
        console.print(f"[yellow]interrupted.[/]{resume if isinstance(cli.command, Run) else ''}")
        return 130


if __name__ == "__main__":
    sys.exit(main())
