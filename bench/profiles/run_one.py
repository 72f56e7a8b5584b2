"""One PPO or ESAPPO training run on InvertedPendulum-v5, for a profiler to sample.

SB3's default PPO hyperparameters (2048-step rollouts: ``n_steps=2048 // n_envs``, batch
64, 10 epochs), torch on one
thread, ``--steps`` env steps over ``--n-envs`` envs in a ``DummyVecEnv``; the ESA agent
with the shipped ``EsaConfig()`` (``--ungated``: ``EsaConfig(gate=None)``) on
``--engine`` ``inprocess`` (the default engine) or ``sidecar`` (a spawned esa-server,
called through the Rust client of ``esa_client._native``). Prints the trainer
process's CPU seconds of ``learn()``.

Usage::

    python bench/profiles/run_one.py --agent ESAPPO --engine inprocess --n-envs 1
"""

from __future__ import annotations

import importlib
import os
import time
from dataclasses import dataclass
from typing import Literal

import torch as th
import tyro
from esa_client.sb3 import ESAPPO
from stable_baselines3 import PPO
from stable_baselines3.common.env_util import make_vec_env

EngineName = Literal["inprocess", "sidecar"]
"""The ESA agent's engines (its ``esa_engine``), as a command-line choice."""


def build(
    agent: str, engine: str, n_envs: int, ungated: bool, seed: int = 0, package: str = "esa_client"
) -> PPO:
    """The model: plain PPO or ESAPPO on ``engine``.

    ``package``: the esa_client package to take ESAPPO from; another name (a copy of an
    earlier version, see ``cpu_ratio.py --before``) compares two versions in one process.
    """
    sb3 = importlib.import_module(f"{package}.sb3")
    env = make_vec_env("InvertedPendulum-v5", n_envs=n_envs, seed=seed)
    # 2048-step rollouts whatever the env count (SB3's default with 1 env): with 8 envs
    # SB3's n_steps=2048 would collect 16,384 steps before the first update, so ESAPPO's
    # head would never be fitted within 12,288 steps.
    common = dict(n_steps=2048 // n_envs, seed=seed, device="cpu", verbose=0)
    if agent == "PPO":
        return PPO("MlpPolicy", env, **common)
    esa = sb3.EsaConfig(gate=None) if ungated else sb3.EsaConfig()
    model: PPO = sb3.ESAPPO("MlpPolicy", env, esa=esa, esa_engine=engine, **common)
    return model


@dataclass
class Args:
    """One training run, for a profiler to watch."""

    agent: Literal["PPO", "ESAPPO"] = "ESAPPO"
    """The agent to train."""
    engine: EngineName = "inprocess"
    """ESAPPO's engine."""
    n_envs: int = 1
    """Training envs."""
    steps: int = 12_288
    """Training steps."""
    ungated: bool = False
    """ESAPPO without its gate (``EsaConfig(gate=None)``)."""


def main(args: Args) -> None:
    """Trains once and prints the CPU seconds."""
    th.set_num_threads(1)
    os.environ.setdefault("ESA_SERVER_BIN", "target/release/esa-server")
    model = build(args.agent, args.engine, args.n_envs, args.ungated)
    cpu, wall = time.process_time(), time.perf_counter()
    model.learn(args.steps)
    cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
    if isinstance(model, ESAPPO):
        model.esa_close()
    print(f"{args.agent} {args.engine} n_envs={args.n_envs}: cpu {cpu:.2f} s, wall {wall:.2f} s")


if __name__ == "__main__":
    main(tyro.cli(Args, config=(tyro.conf.FlagCreatePairsOff,)))
