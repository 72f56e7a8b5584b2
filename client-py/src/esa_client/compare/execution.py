"""Runs a list of runs in worker processes with a ``rich`` progress display.

Workers are ``spawn``-ed processes (fresh interpreters: no forked torch or
gRPC state) limited to one torch/BLAS thread each, so ``--jobs N`` uses N
cores. Each worker trains one run at a time and writes its results itself
(atomically, see :mod:`esa_experiments.runs`), so an interrupted session
loses only the runs in flight. Progress comes back through a queue, at most a
few messages per second per job.
"""

from __future__ import annotations

import contextlib
import ctypes
import multiprocessing as mp
import os
import queue
import signal
import sys
import time
import traceback
from collections.abc import Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass
from multiprocessing.context import SpawnContext
from multiprocessing.managers import SyncManager
from pathlib import Path

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TaskID,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

from esa_experiments.evaluation import ProgressFn
from esa_experiments.runs import RunSpec, RunStore

_THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")
_REPORT_INTERVAL = 0.5  # seconds between two progress messages of one job


@dataclass(frozen=True)
class Outcome:
    """How one run ended.

    Attributes:
        spec: the run.
        seconds: wall-clock of the whole run (training, evaluation, writing).
        error: formatted traceback if the run failed, else None.
        skipped: another runner had finished the run (same fingerprint) by the time a
            worker took it up, so this one did not run it again.
    """

    spec: RunSpec
    seconds: float
    error: str | None = None
    skipped: bool = False


def pin_server_binary() -> str:
    """Resolves the esa-server binary once and makes every worker use it.

    Without ``ESA_SERVER_BIN`` each spawned server would look the binary up
    itself (possibly running ``cargo build``, and possibly getting a different
    build midway through a study); resolving it here (building at most once)
    keeps all runs of a session on one binary. The lookup is the client's
    (:func:`esa_client.sidecar.find_server_binary`: ``ESA_SERVER_BIN``, the
    ``esa-server`` wheel, then a checkout's build), with this
    repository as the checkout when experiments runs from one.
    """
    from esa_client.sidecar import BINARY_ENV, find_server_binary

    path = str(find_server_binary(checkout=Path(__file__).resolve().parents[3]))
    os.environ[BINARY_ENV] = path
    return path


def _init_worker(studies: list[str]) -> None:
    import torch

    torch.set_num_threads(1)
    _die_with_runner()
    _import_run_code(studies)


def _import_run_code(studies: list[str]) -> None:
    """Imports the trainers and the runs' studies when the worker starts, not at its first run.

    Their imports are otherwise lazy, so a runner going for hours would load code from the
    working tree as it is at each worker's first run of a kind, and a file caught
    half-edited would fail runs at 0 s. Imported here, a worker runs the code of its start
    throughout.
    """
    import esa_client.sb3  # noqa: F401

    from esa_experiments.studies import load_study

    for name in studies:
        load_study(name)


def _die_with_runner() -> None:
    """Linux: the worker is killed when the runner dies.

    Otherwise a killed runner's workers finish their runs in flight beside a restarted
    runner, which starts the same runs again (harmless, as writes are atomic and runs
    deterministic, but it costs their cores), and then wait forever.
    """
    if sys.platform.startswith("linux"):
        pr_set_pdeathsig = 1
        ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, signal.SIGKILL)


def _manager(ctx: SpawnContext) -> SyncManager:
    """A started Manager (for the progress queue) whose process dies with the runner.

    A killed runner's Manager would otherwise live on, and with it the resource tracker and
    the runner's stdout, which it inherited: a caller reading that to its end waits forever.
    """
    manager = SyncManager(ctx=ctx)
    manager.start(_die_with_runner)
    return manager


Messages = queue.Queue[tuple[int, int]]
"""Progress messages from the workers: (job, steps done)."""


def _throttled(messages: Messages, job: int) -> ProgressFn:
    last = 0.0

    def report(done: int) -> None:
        nonlocal last
        now = time.monotonic()
        if now - last >= _REPORT_INTERVAL:
            last = now
            messages.put((job, done))

    return report


def run_one(spec: RunSpec, base: Path | None, progress: ProgressFn | None = None) -> Outcome:
    """Runs one run in this process and writes its results; never raises for run errors."""
    from esa_experiments.studies import load_study

    start = time.perf_counter()
    store = RunStore(spec.study, spec.budget, base)
    # Runners may share a results folder (a second machine, a second job list): the list of
    # pending runs was made at start, so look again before minutes of work.
    if store.status(spec) == "done":
        return Outcome(spec, 0.0, skipped=True)
    try:
        result = load_study(spec.study).run(spec, progress or (lambda _: None))
        result.meta["seconds"] = time.perf_counter() - start
        if spec.config.get("uses_server"):
            result.meta["esa_server_bin"] = os.environ.get("ESA_SERVER_BIN")
        store.write(spec, result)
    except Exception:  # one failed run must not stop the others
        return Outcome(spec, time.perf_counter() - start, traceback.format_exc())
    return Outcome(spec, time.perf_counter() - start)


def _worker(spec: RunSpec, base: Path | None, messages: Messages, job: int) -> Outcome:
    return run_one(spec, base, _throttled(messages, job))


def execute(
    specs: list[RunSpec], jobs: int, base: Path | None = None, console: Console | None = None
) -> list[Outcome]:
    """Runs ``specs`` on ``jobs`` worker processes, showing one bar per running job.

    Args:
        specs: the runs to do (already filtered to the pending ones).
        jobs: number of worker processes (>= 1).
        base: folder holding the results folders (default: ``experiments/``).
        console: where to draw the progress display.

    Returns:
        One outcome per spec, in completion order.
    """
    if jobs < 1:
        raise ValueError(f"expected jobs >= 1, got {jobs}")
    for var in _THREAD_VARS:
        os.environ.setdefault(var, "1")
    console = console or Console()
    if any(spec.config.get("uses_server") for spec in specs):
        _pin_or_warn(console)
    ctx = mp.get_context("spawn")
    outcomes: list[Outcome] = []
    columns = (
        TextColumn("{task.description}", justify="left"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
    )
    with (
        _interrupt_on_term(),
        _manager(ctx) as manager,
        Progress(*columns, console=console) as progress,
        ProcessPoolExecutor(
            jobs,
            mp_context=ctx,
            initializer=_init_worker,
            initargs=(sorted({spec.study for spec in specs}),),
        ) as pool,
    ):
        messages = manager.Queue()
        overall = progress.add_task("[bold]all runs", total=len(specs))
        bars: dict[int, TaskID] = {}
        finished: set[int] = set()
        futures: dict[Future[Outcome], int] = {}
        try:
            for job, spec in enumerate(specs):
                futures[pool.submit(_worker, spec, base, messages, job)] = job
            while futures:
                _drain(messages, progress, bars, finished, specs)
                for future in [f for f in futures if f.done()]:
                    job = futures.pop(future)
                    finished.add(job)
                    outcome = future.result()
                    outcomes.append(outcome)
                    if job in bars:
                        progress.remove_task(bars.pop(job))
                    progress.advance(overall)
                    status = (
                        "[red]FAILED"
                        if outcome.error
                        else "[yellow]skipped (done meanwhile)"
                        if outcome.skipped
                        else "[green]done"
                    )
                    progress.console.print(
                        f"{status}[/] {outcome.spec.label} ({outcome.seconds:.0f}s)"
                    )
        except KeyboardInterrupt:
            _stop_workers(pool)
            raise
    return outcomes


def _pin_or_warn(console: Console) -> None:
    """Pins the esa-server binary (:func:`pin_server_binary`), or says why not and goes on.

    The SB3 drop-ins run ESA in-process, so most "ESA" runs need no binary; a run that
    does start a server fails alone, with the client's error naming how to get one.
    """
    from esa_client.errors import EsaError

    try:
        console.print(f"esa-server: {pin_server_binary()}")
    except EsaError as err:
        console.print(f"[yellow]esa-server not found; runs that start a server will fail:[/] {err}")


def _stop_workers(pool: ProcessPoolExecutor) -> None:
    """Kills the workers at once: an interrupted session drops its runs in flight.

    Leaving the pool's block would otherwise wait for them (minutes each); their results
    are written atomically, so a killed run leaves nothing and runs again on resume.
    ProcessPoolExecutor has no public way to end its workers before Python 3.14.
    """
    for process in list((pool._processes or {}).values()):  # noqa: SLF001
        process.kill()
    pool.shutdown(wait=False, cancel_futures=True)


@contextlib.contextmanager
def _interrupt_on_term() -> Iterator[None]:
    """Within the block SIGTERM (``timeout``, ``kill``, a scheduler) acts as Ctrl-C does."""

    def interrupt(_signum: int, _frame: object) -> None:
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _drain(
    messages: Messages,
    progress: Progress,
    bars: dict[int, TaskID],
    finished: set[int],
    specs: list[RunSpec],
) -> None:
    """Applies the queued progress messages (waits briefly for the first)."""
    latest: dict[int, int] = {}
    try:
        job, done = messages.get(timeout=0.2)
        while True:
            latest[job] = done
            job, done = messages.get_nowait()
    except queue.Empty:
        pass
    for job, done in latest.items():
        if job in finished:  # a late message of a run that already ended
            continue
        if job not in bars:
            bars[job] = progress.add_task(specs[job].label, total=specs[job].config["total_steps"])
        progress.update(bars[job], completed=done)
