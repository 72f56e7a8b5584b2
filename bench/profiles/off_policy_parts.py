"""Where ESATD3's time goes inside training, against plain TD3: the ESA step, and TD3's own.

Trains TD3 or ESATD3 (SB3 defaults, InvertedPendulum-v5, 1 env, 800 learning-starts steps,
torch on one thread) with timers around TD3's gradient updates (``train``), SB3's action
sampling, ESA's override of it (``_sample_action``: the sampling, the gate and the ESA
step), the runtime's ESA step (``EsaRuntime.step``) and the probed critic's forward passes
(``_probe_q``). Prints the seconds and calls of each.

It separates ESA's own cost from what ESA changes in TD3: with ``--esa-learning-rate 0``
ESATD3 runs every ESA step but executes TD3's actions, so its ``train`` must take what
TD3's does; with ESA's shifts the trajectory differs, and so can the time of TD3's own
updates, as between TD3's seeds (``--seed``).

Usage::

    OMP_NUM_THREADS=1 python bench/profiles/off_policy_parts.py --agent ESATD3
        [--engine inprocess|sidecar] [--steps 4000] [--seed 0] [--esa-learning-rate 0]
"""

from __future__ import annotations

import os
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import torch as th
import tyro
from esa_client.common.runtime import EsaRuntime
from esa_client.sb3 import ESATD3, EsaConfig
from esa_client.sb3.off_policy import OffPolicyEsaMixin
from run_one import EngineName
from stable_baselines3 import TD3
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm

TIMED = [
    (TD3, "train", "train"),
    (OffPolicyAlgorithm, "_sample_action", "sb3_sample_action"),
    (OffPolicyEsaMixin, "_sample_action", "esa_sample_action"),
    (EsaRuntime, "step", "esa_step"),
    (OffPolicyEsaMixin, "_probe_q", "critic_forward"),
]


def timed(method: Callable, key: str, seconds: dict, calls: dict) -> Callable:
    """``method``, adding the seconds of each call to ``seconds[key]``."""

    def wrapper(*args, **kwargs):
        start = time.perf_counter()
        try:
            return method(*args, **kwargs)
        finally:
            seconds[key] += time.perf_counter() - start
            calls[key] += 1

    return wrapper


@dataclass
class Args:
    """Where ESATD3's time goes inside training, against plain TD3."""

    agent: Literal["TD3", "ESATD3"] = "ESATD3"
    """The agent to train."""
    engine: EngineName = "inprocess"
    """ESATD3's engine."""
    steps: int = 4000
    """Training steps."""
    seed: int = 0
    """Seed of the agent and the env."""
    esa_learning_rate: float | None = None
    """ESA's learning rate (default: the shipped config's)."""


def main(args: Args) -> None:
    """Trains once with the timers in place and prints what they measured."""
    th.set_num_threads(1)
    os.environ.setdefault("ESA_SERVER_BIN", "target/release/esa-server")
    seconds: dict[str, float] = defaultdict(float)
    calls: dict[str, int] = defaultdict(int)
    for cls, name, key in TIMED:
        setattr(cls, name, timed(getattr(cls, name), key, seconds, calls))
    env = make_vec_env("InvertedPendulum-v5", n_envs=1, seed=args.seed)
    common = dict(seed=args.seed, device="cpu", verbose=0, learning_starts=800)
    if args.agent == "TD3":
        model = TD3("MlpPolicy", env, **common)
    else:
        if args.esa_learning_rate is not None:
            common["esa"] = EsaConfig.off_policy(learning_rate=args.esa_learning_rate)
        model = ESATD3("MlpPolicy", env, esa_engine=args.engine, **common)
    start = time.perf_counter()
    model.learn(args.steps)
    label = args.agent if args.agent == "TD3" else f"{args.agent} [{args.engine}]"
    print(f"{label} seed {args.seed}: learn() {time.perf_counter() - start:.2f} s")
    for key, total in seconds.items():
        print(f"  {key:>18}: {total:6.2f} s, {calls[key]} calls")
    if isinstance(model, ESATD3):
        model.esa_close()


if __name__ == "__main__":
    main(tyro.cli(Args))
