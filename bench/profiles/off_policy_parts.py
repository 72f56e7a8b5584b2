"""Where an off-policy drop-in's time goes inside training: the ESA step, and its base's own.

Trains TD3, ESATD3, SAC or ESASAC (SB3 defaults, InvertedPendulum-v5, 1 env, 800
learning-starts steps, torch on one thread) with timers around the gradient updates
(``train``), SB3's action sampling, ESA's override of it (``_sample_action``: the sampling,
the gate and the ESA step), the runtime's ESA step (``EsaRuntime.step``) and the probed
critic's forward passes (``_probe_q``). Prints the seconds and calls of each.

It separates ESA's own cost from what ESA changes in its base: with
``--esa-learning-rate 0`` a drop-in runs every ESA step but executes its base's actions, so
its ``train`` must take what the base's does; with ESA's shifts the trajectory differs, and
so can the time of the base's own updates, as between seeds (``--seed``).

Usage::

    OMP_NUM_THREADS=1 python bench/profiles/off_policy_parts.py --agent ESATD3|ESASAC|TD3|SAC
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
from esa_client.sb3 import ESASAC, ESATD3, EsaConfig
from esa_client.sb3.off_policy import OffPolicyEsaMixin
from run_one import EngineName
from stable_baselines3 import SAC, TD3
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm

TIMED = [
    (TD3, "train", "train"),
    (SAC, "train", "train"),
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
    """Where an off-policy drop-in's time goes inside training, against its base."""

    agent: Literal["TD3", "ESATD3", "SAC", "ESASAC"] = "ESATD3"
    """The agent to train."""
    engine: EngineName = "inprocess"
    """The drop-in's engine."""
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
    cls = {"TD3": TD3, "SAC": SAC, "ESATD3": ESATD3, "ESASAC": ESASAC}[args.agent]
    drop_in = issubclass(cls, OffPolicyEsaMixin)
    if drop_in:
        common["esa_engine"] = args.engine
        if args.esa_learning_rate is not None:
            common["esa"] = EsaConfig.off_policy(learning_rate=args.esa_learning_rate)
    model = cls("MlpPolicy", env, **common)
    start = time.perf_counter()
    model.learn(args.steps)
    label = f"{args.agent} [{args.engine}]" if drop_in else args.agent
    print(f"{label} seed {args.seed}: learn() {time.perf_counter() - start:.2f} s")
    for key, total in seconds.items():
        print(f"  {key:>18}: {total:6.2f} s, {calls[key]} calls")
    if drop_in:
        model.esa_close()


if __name__ == "__main__":
    main(tyro.cli(Args))
