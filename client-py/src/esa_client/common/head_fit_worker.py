"""The advantage head's fit in a worker process, beside PPO's own update.

ESAPPO fits its head on every rollout: about 0.3 s of torch compute per 12,288 steps, 0.04x
of PPO's wall-clock with 1 env and 0.08x with 8 (``bench/profiles/README.md``). The fit needs
nothing PPO's update changes, so a second process runs it while PPO updates the policy, on
a core PPO leaves idle. A thread cannot: both loops are many small torch calls under the GIL.

The worker is stateless. A :class:`FitJob` carries the head's and Adam's state, the
minibatch generator and the data; the :class:`FitResult` carries them back. So a fit there
runs the same float32 operations as a fit here (the same torch, its thread count set as the
trainer's), and whenever the worker cannot answer (not started yet, busy with another model,
gone) the trainer fits here from its untouched state, with the same bits.

One worker serves every model of the process (started by the first that asks, ended at
exit or when its stdin closes): a fresh interpreter running this module, never a fork of
the trainer, so an unguarded training script is not run again and no lock held by another
thread is inherited.
"""

from __future__ import annotations

import atexit
import logging
import os
import pickle
import select
import signal
import struct
import subprocess
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import IO, Any

import numpy as np
import torch as th

from .advantage_head import AdvantageHead, Rollout, fit

_log = logging.getLogger(__name__)

_FRAME = struct.Struct("<Q")
"""Each message: its length, then its pickle."""
_READY = "ready"
_POLL_S = 1.0
"""How often a trainer waiting for a fit checks that the worker is still alive."""
_CHANNEL_ERRORS = (OSError, EOFError, RuntimeError, pickle.PickleError)
"""What a failed worker or a broken channel raises: the trainer fits the head itself."""


@dataclass
class FitResult:
    """The head, optimizer and generator after a fit, and its mean loss."""

    head: dict[str, th.Tensor]
    optimizer: dict[str, Any]
    rng: np.random.Generator
    loss: float

    def apply(self, head: AdvantageHead, optimizer: th.optim.Optimizer) -> np.random.Generator:
        """Writes the fit into the trainer's head and optimizer; returns the generator."""
        head.load_state_dict(self.head)
        optimizer.load_state_dict(self.optimizer)
        # As fit() counts it: the Rust copy of the head is taken again after a fit.
        head.fits += 1
        return self.rng


@dataclass
class FitJob:
    """Everything :func:`~esa_client.common.advantage_head.fit` reads and writes, picklable."""

    sizes: tuple[int, int, int]
    """The head's features, action dimension and hidden units."""
    dtype: th.dtype
    fused: bool | None
    head: dict[str, th.Tensor]
    optimizer: dict[str, Any]
    rng: np.random.Generator
    rollouts: list[Rollout]
    epochs: int
    batch_size: int
    threads: int

    @classmethod
    def of(
        cls,
        head: AdvantageHead,
        optimizer: th.optim.Optimizer,
        rollouts: list[Rollout],
        *,
        rng: np.random.Generator,
        epochs: int,
        batch_size: int,
    ) -> FitJob:
        """The job of ``fit(head, optimizer, rollouts, ...)`` (sending it copies the states)."""
        first, _, last = head._linears
        return cls(
            sizes=(first.in_features, last.out_features, first.out_features),
            dtype=first.weight.dtype,
            fused=optimizer.defaults.get("fused"),
            head=head.state_dict(),
            optimizer=optimizer.state_dict(),
            rng=rng,
            rollouts=rollouts,
            epochs=epochs,
            batch_size=batch_size,
            threads=th.get_num_threads(),
        )

    def run(self) -> FitResult:
        """Fits a copy of the head as ``fit`` would have fitted the original."""
        if th.get_num_threads() != self.threads:
            th.set_num_threads(self.threads)
        head = AdvantageHead(*self.sizes).to(self.dtype)
        head.load_state_dict(self.head)
        optimizer = th.optim.Adam(head.parameters(), fused=self.fused)
        optimizer.load_state_dict(self.optimizer)
        loss = fit(
            head,
            optimizer,
            self.rollouts,
            epochs=self.epochs,
            batch_size=self.batch_size,
            rng=self.rng,
        )
        return FitResult(head.state_dict(), optimizer.state_dict(), self.rng, loss)


PendingFit = Callable[[], "FitResult | None"]
"""A fit sent to the worker: waits for it, and gives None if the worker failed meanwhile."""


def _write(stream: IO[bytes], message: object) -> None:
    data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    stream.write(_FRAME.pack(len(data)) + data)
    stream.flush()


def _read(stream: IO[bytes]) -> object:
    """The next message; EOFError when the other side has gone."""
    header = stream.read(_FRAME.size)
    if len(header) < _FRAME.size:
        raise EOFError("the other side of the head-fit channel closed it")
    (size,) = _FRAME.unpack(header)
    data = stream.read(size)
    if len(data) < size:
        raise EOFError("the head-fit channel closed mid-message")
    return pickle.loads(data)


class HeadFitWorker:
    """The trainer's side of the worker process: one job at a time, never blocking to start."""

    def __init__(self) -> None:
        """Starts the worker; it answers once torch is imported and warm there (seconds)."""
        env = dict(os.environ)
        # The worker imports this package as the trainer found it (an installed wheel, a
        # checkout on sys.path).
        env["PYTHONPATH"] = os.pathsep.join(p for p in sys.path if p)
        self._process = subprocess.Popen(
            [sys.executable, "-c", f"from {__name__} import main; main()"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            env=env,
        )
        self._ready = False
        self._broken = False
        self._lock = threading.Lock()

    @property
    def usable(self) -> bool:
        """False once the worker failed: the trainer fits in-process from then on."""
        return not self._broken

    def wait_ready(self, timeout: float) -> bool:
        """Waits up to ``timeout`` seconds for the worker to start; True if it has."""
        with self._lock:
            return self._check_ready(timeout)

    def submit(self, job: FitJob) -> PendingFit | None:
        """Sends ``job`` if the worker is free and started, else None (fit in-process).

        Returns:
            A function that waits for the result: a :class:`FitResult`, or None if the
            worker failed meanwhile (then the trainer's state is as the job copied it).
        """
        if self._broken or not self._lock.acquire(blocking=False):
            return None
        try:
            if not self._check_ready(0.0):
                self._lock.release()
                return None
            assert self._process.stdin is not None
            _write(self._process.stdin, job)
        except BaseException as err:
            # Interrupted mid-message too (Ctrl+C): the channel is out of step for good.
            self._fail(err)
            self._lock.release()
            if isinstance(err, _CHANNEL_ERRORS):
                return None
            raise
        return self._result

    def _result(self) -> FitResult | None:
        try:
            stdout = self._process.stdout
            assert stdout is not None
            while not select.select([stdout], [], [], _POLL_S)[0]:
                if self._process.poll() is not None:
                    raise EOFError(f"it exited with status {self._process.returncode}")
            answer = _read(stdout)
            if not isinstance(answer, FitResult):
                raise RuntimeError(f"its fit failed: {answer}")
            return answer
        except BaseException as err:
            # Interrupted too (Ctrl+C): the answer left in the pipe would pass for the next
            # job's.
            self._fail(err)
            if isinstance(err, _CHANNEL_ERRORS):
                return None
            raise
        finally:
            self._lock.release()

    def _check_ready(self, timeout: float) -> bool:
        if self._ready:
            return True
        stdout = self._process.stdout
        assert stdout is not None
        try:
            if select.select([stdout], [], [], timeout)[0]:
                if _read(stdout) != _READY:
                    raise RuntimeError("it did not announce itself")
                self._ready = True
        except _CHANNEL_ERRORS as err:
            self._fail(err)
        return self._ready

    def _fail(self, err: BaseException) -> None:
        _log.warning(
            "the advantage head's fit worker failed (%s: %s): ESAPPO fits its head "
            "in-process from now on, with the same results",
            type(err).__name__,
            err,
        )
        self._broken = True
        self.close()

    def close(self) -> None:
        """Ends the worker now."""
        # It holds no state; waiting for it to notice its closed stdin could hold the
        # trainer's exit for seconds (torch's import, a fit).
        for stream in (self._process.stdin, self._process.stdout):
            if stream is not None:
                stream.close()
        self._process.kill()
        self._process.wait()


_SHARED: HeadFitWorker | None = None
_SHARED_LOCK = threading.Lock()


def shared_worker(force: bool = False) -> HeadFitWorker | None:
    """The process's worker, started on the first call; None where it does not serve.

    Args:
        force: Serve even with one CPU available to this process. Without it, none serves
            there (the fit would take PPO's own core).

    Returns:
        The worker; None with one CPU (unless forced), on Windows (``select`` cannot wait on
        a pipe there) or once the worker failed.
    """
    global _SHARED
    with _SHARED_LOCK:
        if _SHARED is not None:
            return _SHARED if _SHARED.usable else None
        if sys.platform == "win32" or not (force or available_cpus() >= 2):
            return None
        _SHARED = HeadFitWorker()
        atexit.register(_SHARED.close)
        return _SHARED


def available_cpus() -> int:
    """The CPUs this process may run on (all of the machine's where that cannot be read)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS has no sched_getaffinity
        return os.cpu_count() or 1


def _warm_up() -> None:
    """A tiny fit: torch's first optimizer step loads modules for a second or more."""
    head = AdvantageHead(1, 1, hidden=1)
    optimizer = th.optim.Adam(head.parameters(), fused=True)
    one = th.zeros(1, 1)
    rollout = Rollout(one, one, th.zeros(1))
    rng = np.random.default_rng(0)
    FitJob.of(head, optimizer, [rollout], rng=rng, epochs=1, batch_size=1).run()


def main() -> None:
    """The worker: announces itself, then answers each job until its stdin closes.

    It ends quietly when its trainer has gone (a closed stdin, or a closed channel when it
    writes).
    """
    # Ctrl+C reaches the whole process group: the trainer decides, and the worker ends when
    # its stdin closes.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # Its own stdout is the channel: anything printed goes to stderr instead.
    channel = os.fdopen(os.dup(sys.stdout.fileno()), "wb")
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())
    _warm_up()
    try:
        _write(channel, _READY)
        while True:
            job = _read(sys.stdin.buffer)
            try:
                answer: object = job.run() if isinstance(job, FitJob) else f"not a FitJob: {job!r}"
            except Exception as err:  # noqa: BLE001 - reported to the trainer, which fits
                answer = f"{type(err).__name__}: {err}"
            _write(channel, answer)
    except (EOFError, BrokenPipeError):
        return
