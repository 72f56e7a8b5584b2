"""``esa-compare``: the command line (also ``python -m esa_client.compare``).

    esa-compare --env Hopper-v5 --algo ppo

trains the baseline, ESA and its placebo on seeds 0-9, then writes the curves, the
verdicts and ``RESULTS.md`` into ``--out``. The same command again goes on where it
stopped (finished runs are kept, lost ones redone) and does nothing once all is done.
"""

from __future__ import annotations

import argparse
import os
import re
import shlex
import sys
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

from esa_client.compare.hyperparams import SOURCES, resolve
from esa_client.compare.rules import ALGOS, ARMS, DEFAULT_ARMS, Rules, fix_rules
from esa_client.compare.runs import RunFolder, parse_seeds

DEFAULT_STEPS = 100_000
"""The budget when neither ``--steps`` nor the settings' ``n_timesteps`` give one."""


@dataclass(frozen=True)
class CompareArgs:
    """The command's arguments (see ``esa-compare --help``)."""

    env: str
    algo: str
    arms: tuple[str, ...] = DEFAULT_ARMS
    seeds: str = "10"
    steps: int | None = None
    eval_every: int | None = None
    eval_episodes: int = 10
    hyperparams: str = "auto"
    out: Path | None = None
    jobs: int = os.cpu_count() or 1
    ray: str | None = None
    dry_run: bool = False


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="esa-compare",
        description="Does ESA help on my task? Trains the baseline, ESA and its controls on "
        "the same seeds and judges them with a placebo-controlled verdict.",
    )
    parser.add_argument("--env", required=True, help="a gymnasium env id, or module:factory")
    parser.add_argument("--algo", required=True, choices=ALGOS)
    parser.add_argument(
        "--arms",
        default=",".join(DEFAULT_ARMS),
        help=f"comma-separated arms from {', '.join(ARMS)} (default: %(default)s)",
    )
    parser.add_argument(
        "--seeds",
        default="10",
        help="a number of seeds (from 0), or seeds like 0-9 or 0,3,5-7 (default: %(default)s)",
    )
    parser.add_argument(
        "--steps",
        type=int,
        help=f"env steps per run (default: the settings' n_timesteps, else {DEFAULT_STEPS:,})",
    )
    parser.add_argument(
        "--eval-every", type=int, help="env steps between evaluations (default: steps / 20)"
    )
    parser.add_argument(
        "--eval-episodes",
        type=int,
        default=10,
        help="deterministic episodes per evaluation (default: 10)",
    )
    parser.add_argument(
        "--hyperparams",
        default="auto",
        help="auto (RL Zoo3's tuned set if it has the env, else SB3's defaults), zoo, default, "
        "or a zoo-format YAML file (default: %(default)s)",
    )
    parser.add_argument(
        "--out", type=Path, help="results folder (default: esa-compare-<env>-<algo>)"
    )
    parser.add_argument(
        "--jobs",
        type=int,
        default=os.cpu_count() or 1,
        help="parallel runs here (default: one per core)",
    )
    parser.add_argument(
        "--ray",
        metavar="ADDRESS",
        help="run each run as a Ray task on this cluster (auto, ray://..., local)",
    )
    parser.add_argument("--dry-run", action="store_true", help="say what would run, run nothing")
    return parser


def parse(argv: Sequence[str] | None = None) -> CompareArgs:
    """Parses the command line (exits with a usage message on bad syntax)."""
    ns = _parser().parse_args(argv)
    return CompareArgs(
        env=ns.env,
        algo=ns.algo,
        arms=tuple(arm.strip() for arm in ns.arms.split(",") if arm.strip()),
        seeds=ns.seeds,
        steps=ns.steps,
        eval_every=ns.eval_every,
        eval_episodes=ns.eval_episodes,
        hyperparams=ns.hyperparams,
        out=ns.out,
        jobs=ns.jobs,
        ray=ns.ray,
        dry_run=ns.dry_run,
    )


def seeds_of(text: str) -> tuple[int, ...]:
    """``"10"`` is seeds 0-9; ranges and lists (``"0-9"``, ``"0,3,5-7"``) are taken as given."""
    if re.fullmatch(r"\d+", text.strip()):
        count = int(text)
        if count < 1:
            raise ValueError(f"expected --seeds >= 1, got {count}")
        return tuple(range(count))
    return tuple(parse_seeds(text))


def rules_of(args: CompareArgs) -> Rules:
    """The comparison's rules from the arguments (settings resolved).

    Raises:
        ValueError: any bad argument, with what was expected.
    """
    if args.hyperparams not in SOURCES and not Path(args.hyperparams).is_file():
        raise ValueError(
            f"expected --hyperparams in {SOURCES} or an existing YAML file, "
            f"got {args.hyperparams!r}"
        )
    from esa_client.compare.training import env_factory

    env_factory(args.env)
    params = resolve(args.hyperparams, args.env, args.algo)
    steps = args.steps or params.n_timesteps or DEFAULT_STEPS
    return Rules(
        env=args.env,
        algo=args.algo,
        arms=args.arms,
        seeds=seeds_of(args.seeds),
        steps=steps,
        eval_every=args.eval_every or max(1, steps // 20),
        eval_episodes=args.eval_episodes,
        hyperparams=asdict(params),
    )


def default_out(env: str, algo: str) -> Path:
    """``esa-compare-<env>-<algo>`` with the env's odd characters made ``-``."""
    return Path(f"esa-compare-{re.sub(r'[^A-Za-z0-9_.]+', '-', env)}-{algo}")


def main(argv: Sequence[str] | None = None) -> int:
    """Runs the comparison; returns the exit status (0 done, 1 failed runs, 2 bad input)."""
    from rich.console import Console

    from esa_client.compare import execution, report
    from esa_client.compare.arms import CompareJob

    console = Console()
    args = parse(argv)
    command = shlex.join(["esa-compare", *(sys.argv[1:] if argv is None else argv)])
    try:
        rules = rules_of(args)
        if args.jobs < 1:
            raise ValueError(f"expected --jobs >= 1, got {args.jobs}")
        folder = RunFolder(args.out or default_out(args.env, args.algo))
        fix_rules(rules, folder)
    except ValueError as err:
        console.print(f"[red]esa-compare:[/] {err}")
        return 2
    specs = rules.specs()
    pending = folder.pending(specs)
    console.print(
        f"{rules.label('esa')} on {rules.env}: {len(specs)} runs ({len(rules.arms)} arms x "
        f"{len(rules.seeds)} seeds, {rules.steps:,} steps each), {len(specs) - len(pending)} "
        f"done, {len(pending)} to do -> {folder.dir}"
    )
    results = folder.dir / "RESULTS.md"
    provenance = folder.dir / "provenance.json"
    if not pending and results.is_file() and provenance.is_file():
        import json

        if json.loads(provenance.read_text()).get("runs_sha256") == report.runs_digest(folder):
            console.print(f"Nothing to do: every run is done and {results} is up to date.")
            return 0
    if args.dry_run:
        for spec in pending:
            console.print(f"  would run {spec.label}")
        return 0
    job = CompareJob(folder.dir)
    try:
        if args.ray:
            outcomes = execution.execute_on_ray(pending, args.ray, job, console)
        elif pending:
            outcomes = execution.execute(pending, min(args.jobs, len(pending)), job, console)
        else:
            outcomes = []
    except KeyboardInterrupt:
        console.print(
            "\n[yellow]Interrupted.[/] Finished runs are kept, the ones in flight left nothing: "
            "run the same command again to go on."
        )
        return 130
    failed = [o for o in outcomes if o.error]
    for outcome in failed:
        console.print(f"[red]FAILED[/] {outcome.spec.label}\n{outcome.error}")
    try:
        sentence = report.write_report(folder, rules, command)
    except FileNotFoundError:
        console.print("[red]No run finished[/]: nothing to report.")
        return 1
    console.print(f"\n{sentence}\nCurves, tables and verdicts: {results}")
    return 1 if failed else 0
