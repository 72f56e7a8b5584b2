"""Where a step sent ahead spends its time inside training, through a native sidecar.

Trains an ESA drop-in (SB3 defaults, InvertedPendulum-v5, 1 env by default; ESAPPO, or
ESASAC / ESATD3 with the bench's 800 learning-starts steps) through a private esa-server
reached with the native client, with a timer around the runtime's whole ESA step
(``EsaRuntime.step``: the critic's evaluation included), ``SessionBatch.step`` (sent ahead), and
its native calls: ``send_step_linear`` (ESAPPO's linear critic) or ``send_step`` (the
critic's values), which queue the step for the batch's stream thread, and
``receive_step`` (taking the answer of the previous step). Prints each one's mean and
percentiles per call.

Usage::

    OMP_NUM_THREADS=1 python bench/profiles/ahead_parts.py [--agent ESAPPO] [--steps N]
        [--n-envs 1]
"""

from __future__ import annotations

import os
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch as th
import tyro
from esa_client import SessionBatch
from esa_client.common.runtime import EsaRuntime
from esa_client.sb3 import ESAPPO, ESASAC, ESATD3
from esa_client.transports.grpc import GrpcStepBatch
from stable_baselines3.common.env_util import make_vec_env

TIMED = [
    (EsaRuntime, "step"),
    (SessionBatch, "step"),
    (GrpcStepBatch, "send_step_linear"),
    (GrpcStepBatch, "send_step"),
    (GrpcStepBatch, "receive_step"),
]
AGENTS = {"ESAPPO": ESAPPO, "ESASAC": ESASAC, "ESATD3": ESATD3}
STEPS = {"ESAPPO": 12_288, "ESASAC": 8_000, "ESATD3": 8_000}
"""The bench's steps per run (``training_overhead.py``)."""


def timed(method: Callable, times: list[float]) -> Callable:
    """``method``, appending the seconds of each call to ``times``."""

    def wrapper(*args, **kwargs):
        start = time.perf_counter()
        try:
            return method(*args, **kwargs)
        finally:
            times.append(time.perf_counter() - start)

    return wrapper


@dataclass
class Args:
    """Where a step sent ahead spends its time inside training, through a native sidecar."""

    agent: Literal["ESAPPO", "ESASAC", "ESATD3"] = "ESAPPO"
    """The ESA drop-in to train."""
    steps: int | None = None
    """Training steps (default: the bench's for the agent)."""
    n_envs: int = 1
    """Training envs."""


def main(args: Args) -> None:
    """Trains once with the timers in place and prints what they measured."""
    steps = args.steps or STEPS[args.agent]
    th.set_num_threads(1)
    os.environ.setdefault("ESA_SERVER_BIN", "target/release/esa-server")
    times: dict[str, list[float]] = defaultdict(list)
    for cls, name in TIMED:
        key = f"{cls.__name__}.{name}"
        setattr(cls, name, timed(getattr(cls, name), times[key]))
    env = make_vec_env("InvertedPendulum-v5", n_envs=args.n_envs, seed=0)
    off_policy = {} if args.agent == "ESAPPO" else {"learning_starts": 800}
    model = AGENTS[args.agent](
        "MlpPolicy",
        env,
        esa_engine="sidecar",
        esa_spawn={},
        seed=0,
        **off_policy,
    )
    start = time.perf_counter()
    model.learn(steps)
    print(f"learn() {time.perf_counter() - start:.2f} s")
    for name, seconds in times.items():
        if not seconds:
            continue  # the other agents' calls
        us = np.array(seconds) * 1e6
        p10, p50, p90, p99 = np.percentile(us, [10, 50, 90, 99])
        print(
            f"{name:>31}: {len(us)} calls, mean {us.mean():.1f} us, p10 {p10:.1f}, "
            f"p50 {p50:.1f}, p90 {p90:.1f}, p99 {p99:.1f}, total {us.sum() / 1e6:.3f} s"
        )
    model.esa_close()


if __name__ == "__main__":
    main(tyro.cli(Args))
