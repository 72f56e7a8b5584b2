"""Runs a list of runs in worker processes with a ``rich`` progress display.

Workers are ``spawn``-ed processes (fresh interpreters: no forked torch or
gRPC state) limited to one torch/BLAS thread each, so ``--jobs N`` uses N
cores. Each worker trains one run at a time and writes its results itself
(atomically, see :mod:`esa_client.compare.runs`), so an interrupted session
loses only the runs in flight. Progress comes back through a queue, at most a
few messages per second per job.

What a run is comes from a :class:`Job`: ``esa-compare``'s trains one arm on the user's
env, the experiments' studies' look the run up in its study.
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
from typing import Protocol

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

from esa_client.compare.evaluation import ProgressFn
from esa_client.compare.runs import RunFolder, RunResult, RunSpec

_THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")
_REPORT_INTERVAL = 0.5  # seconds between two progress messages of one job


class Job(Protocol):
    """What the workers do with a run; pickled into spawned workers, so module-level state.

    ``uses_server`` in a spec's config asks for the esa-server binary to be pinned first.
    """

    def folder(self, spec: RunSpec) -> RunFolder:
        """Where the run's results go."""
        ...

    def prepare(self) -> None:
        """Imports the run code, once per worker, when the worker starts."""
        ...

    def run(self, spec: RunSpec, progress: ProgressFn) -> RunResult:
        """Trains and evaluates the run."""
        ...


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
    (:func:`esa_client.sidecar.find_server_binary`).
    """
    from esa_client.sidecar import BINARY_ENV, find_server_binary

    path = str(find_server_binary())
    os.environ[BINARY_ENV] = path
    return path


def _init_worker(job: Job) -> None:
    """Pins torch to one thread and imports the run code when the worker starts.

    The run code's imports are otherwise lazy, so a runner going for hours would load code
    from the working tree as it is at each worker's first run of a kind, and a file caught
    half-edited would fail runs at 0 s. Imported here, a worker runs the code of its start
    throughout.
    """
    import torch

    torch.set_num_threads(1)
    _die_with_runner()
    job.prepare()


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


def run_one(spec: RunSpec, job: Job, progress: ProgressFn | None = None) -> Outcome:
    """Runs one run in this process and writes its results; never raises for run errors."""
    start = time.perf_counter()
    folder = job.folder(spec)
    # Runners may share a results folder (a second machine, a second job list): the list of
    # pending runs was made at start, so look again before minutes of work.
    if folder.status(spec) == "done":
        return Outcome(spec, 0.0, skipped=True)
    try:
        result = job.run(spec, progress or (lambda _: None))
        result.meta["seconds"] = time.perf_counter() - start
        if spec.config.get("uses_server"):
            result.meta["esa_server_bin"] = os.environ.get("ESA_SERVER_BIN")
        folder.write(spec, result)
    except Exception:  # one failed run must not stop the others
        return Outcome(spec, time.perf_counter() - start, traceback.format_exc())
    return Outcome(spec, time.perf_counter() - start)


def _worker(spec: RunSpec, job: Job, messages: Messages, index: int) -> Outcome:
    return run_one(spec, job, _throttled(messages, index))


def execute(
    specs: list[RunSpec], jobs: int, job: Job, console: Console | None = None
) -> list[Outcome]:
    """Runs ``specs`` on ``jobs`` worker processes, showing one bar per running job.

    Args:
        specs: the runs to do (already filtered to the pending ones).
        jobs: number of worker processes (>= 1).
        job: what a run is and where its results go.
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
            initargs=(job,),
        ) as pool,
    ):
        messages = manager.Queue()
        overall = progress.add_task("[bold]all runs", total=len(specs))
        bars: dict[int, TaskID] = {}
        finished: set[int] = set()
        futures: dict[Future[Outcome], int] = {}
        try:
            for index, spec in enumerate(specs):
                futures[pool.submit(_worker, spec, job, messages, index)] = index
            while futures:
                _drain(messages, progress, bars, finished, specs)
                for future in [f for f in futures if f.done()]:
                    index = futures.pop(future)
                    finished.add(index)
                    outcome = future.result()
                    outcomes.append(outcome)
                    if index in bars:
                        progress.remove_task(bars.pop(index))
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


def start_local_ray(num_cpus: int | None = None, attempts: int = 3) -> None:
    """Starts a Ray instance of this process's own (``address="local"``), never another's.

    Ray waits a fixed 30 s for its raylet to register and, by default, 30 s for its GCS to
    publish its port; on a loaded 2-core machine each has run out. So the GCS gets Ray's
    longer wait (the one of its RocksDB backend) and a start that timed out is tried again.

    Args:
        num_cpus: the CPUs Ray may hand out (default: the host's).
        attempts: starts to try.
    """
    import ray

    os.environ.setdefault("RAY_gcs_server_port_wait_time_s", "120")
    for attempt in range(attempts):
        try:
            ray.init(
                address="local",
                num_cpus=num_cpus,
                include_dashboard=False,
                log_to_driver=False,
                configure_logging=False,
            )
            return
        except Exception as err:
            startup = ("timed out during startup", "Timed out waiting for file")
            if not any(text in str(err) for text in startup) or attempt == attempts - 1:
                raise
            ray.shutdown()


def _ray_run(spec: RunSpec, job: Job) -> RunResult:
    """One run as a Ray task: trained on whichever node Ray chose, written by the driver."""
    import torch

    torch.set_num_threads(1)
    job.prepare()
    start = time.perf_counter()
    result = job.run(spec, lambda _: None)
    result.meta["seconds"] = time.perf_counter() - start
    return result


def execute_on_ray(
    specs: list[RunSpec], address: str, job: Job, console: Console | None = None
) -> list[Outcome]:
    """Runs ``specs`` as Ray tasks (one CPU each) on the cluster at ``address``.

    The tasks return their results and this process writes them, so the results folder
    only needs to exist here. A task whose node is lost is retried by Ray; Ctrl-C cancels
    the tasks in flight and writes nothing of theirs.

    Args:
        specs: the runs to do (already filtered to the pending ones).
        address: the cluster's address (``ray.init``'s: ``auto``, ``ray://host:10001``,
            or ``local`` for a Ray instance of this machine).
        job: what a run is and where its results go.
        console: where to draw the progress display.
    """
    import ray

    console = console or Console()
    # A Ray this call starts is this call's to stop (a caller's own stays up for the caller).
    owned = not ray.is_initialized()
    if owned and address == "local":
        start_local_ray()
    elif owned:
        ray.init(address=address, log_to_driver=False)
    try:
        return _gather(specs, address, job, console)
    finally:
        if owned:
            ray.shutdown()


def _gather(specs: list[RunSpec], address: str, job: Job, console: Console) -> list[Outcome]:
    """Submits ``specs`` as Ray tasks and writes each result as it lands."""
    import ray

    remote = ray.remote(num_cpus=1, max_retries=3)(_ray_run)
    console.print(f"Ray: {ray.cluster_resources().get('CPU', 0):.0f} CPUs at {address}")
    started = time.perf_counter()
    refs = {remote.remote(spec, job): spec for spec in specs}
    outcomes: list[Outcome] = []
    columns = (BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), TimeRemainingColumn())
    with _interrupt_on_term(), Progress(*columns, console=console) as progress:
        overall = progress.add_task("runs", total=len(specs))
        pending = list(refs)
        try:
            while pending:
                done, pending = ray.wait(pending, num_returns=1, timeout=1.0)
                for ref in done:
                    spec = refs[ref]
                    seconds = time.perf_counter() - started
                    try:
                        result = ray.get(ref)
                        job.folder(spec).write(spec, result)
                        outcome = Outcome(spec, float(result.meta["seconds"]))
                    except Exception:  # one failed run must not stop the others
                        outcome = Outcome(spec, seconds, traceback.format_exc())
                    outcomes.append(outcome)
                    progress.advance(overall)
                    status = "[red]FAILED" if outcome.error else "[green]done"
                    progress.console.print(f"{status}[/] {spec.label} ({outcome.seconds:.0f}s)")
        except KeyboardInterrupt:
            for ref in pending:
                ray.cancel(ref, force=True)
            raise
    return outcomes
