"""CPU-time and wall-clock ratios ESAPPO / PPO, measured in one process with alternating runs.

For a loaded host, where wall-clock ratios mean little: each run's ``learn()`` is timed
with ``time.process_time()`` (this process's CPU seconds, all threads) and, for a spawned
sidecar, the esa-server's CPU seconds too (read from ``/proc`` just before it is
stopped). PPO and the ESAPPO variants run in turn, ``--repeats`` times per env count, so
slow phases of the host hit all alike. Settings as ``bench/profiles/run_one.py``:
InvertedPendulum-v5, SB3's default PPO hyperparameters, torch on one thread, the shipped
``EsaConfig()``. Wall-clock ratios are reported beside the CPU-time ones: on a quiet host
they are what a user sees, and work moved onto other threads shows only there.

Usage::

    python bench/python/cpu_ratio.py [--n-envs 1,8] [--repeats 3] \
        [--engines inprocess,sidecar] [--before DIR]

With ``--before DIR`` (``DIR/esa_client_before``: e.g. ``cp -r client-py/src/esa_client``
of an earlier commit), the earlier ESAPPO runs in the same alternation: a before/after
comparison in one process.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch as th
import tyro

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "profiles"))
from run_one import build  # noqa: E402


def children_cpu_seconds() -> float:
    """User + system CPU seconds of this process's live child processes (a sidecar)."""
    total = 0.0
    tick = os.sysconf("SC_CLK_TCK")
    for task in Path("/proc/self/task").iterdir():
        try:
            pids = (task / "children").read_text().split()
        except OSError:
            continue
        for pid in pids:
            try:
                fields = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
            except OSError:
                continue
            total += (int(fields[11]) + int(fields[12])) / tick
    return total


def run(
    agent: str, engine: str, n_envs: int, steps: int, package: str = "esa_client"
) -> tuple[float, float, float]:
    """One training: the trainer's CPU seconds of learn(), the sidecar's, learn()'s wall seconds."""
    model = build(agent, engine, n_envs, ungated=False, package=package)
    cpu, wall = time.process_time(), time.perf_counter()
    model.learn(steps)
    cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
    server = children_cpu_seconds()
    if agent != "PPO":
        model.esa_close()  # type: ignore[attr-defined]
    model.get_env().close()
    return cpu, server, wall


@dataclass
class Args:
    """CPU-time and wall-clock ratios ESAPPO / PPO, in alternating runs."""

    n_envs: str = "1,8"
    """Numbers of training envs, comma-separated."""
    engines: str = "inprocess,sidecar"
    """ESAPPO engines, comma-separated."""
    steps: int = 12_288
    """Training steps per run."""
    repeats: int = 3
    """Runs per agent and number of envs."""
    out: str = ""
    """JSON of the ratios (empty: print only)."""
    before: str = ""
    """A folder holding a copy of an earlier esa_client named esa_client_before: its ESAPPO
    runs alternate with the current one's."""


def main(args: Args) -> None:
    """Alternates PPO and the ESAPPO engines; prints and writes the median ratios."""
    th.set_num_threads(1)
    os.environ.setdefault("ESA_SERVER_BIN", "target/release/esa-server")
    configs = [("PPO", "inprocess", "")] + [("ESAPPO", e, "") for e in args.engines.split(",")]
    if args.before:
        # A copy of an earlier esa_client renamed esa_client_before, found on sys.path.
        sys.path.insert(0, args.before)
        configs += [("ESAPPO", e, "esa_client_before") for e in args.engines.split(",")]
    results = []
    for n_envs in (int(n) for n in args.n_envs.split(",")):
        cpu: dict[str, list[float]] = {}
        walls: dict[str, list[float]] = {}
        for _ in range(args.repeats):
            for agent, engine, package in configs:
                name = agent if agent == "PPO" else f"{agent} [{engine}]"
                name += " before" if package else ""
                trainer, server, wall = run(
                    agent, engine, n_envs, args.steps, package or "esa_client"
                )
                cpu.setdefault(name, []).append(trainer + server)
                walls.setdefault(name, []).append(wall)
                print(
                    f"{n_envs} env(s) {name:<26} cpu {trainer:6.2f} s + server {server:5.2f} s"
                    f", wall {wall:6.2f} s",
                    flush=True,
                )
        for name, seconds in cpu.items():
            if name == "PPO":
                continue
            ratios = np.asarray(seconds) / np.asarray(cpu["PPO"])
            wall_ratios = np.asarray(walls[name]) / np.asarray(walls["PPO"])
            results.append(
                {
                    "n_envs": n_envs,
                    "agent": name,
                    "cpu": seconds,
                    "ppo_cpu": cpu["PPO"],
                    "ratio_median": float(np.median(ratios)),
                    "ratios": ratios.tolist(),
                    "wall": walls[name],
                    "ppo_wall": walls["PPO"],
                    "wall_ratio_median": float(np.median(wall_ratios)),
                    "wall_ratios": wall_ratios.tolist(),
                }
            )
            print(
                f"{n_envs} env(s) {name} / PPO CPU-time ratio: "
                f"median {np.median(ratios):.3f} {ratios.round(3)}; wall-clock ratio: "
                f"median {np.median(wall_ratios):.3f} {wall_ratios.round(3)}"
            )
    if args.out:
        Path(args.out).write_text(
            json.dumps({"args": dataclasses.asdict(args), "rows": results}, indent=2)
        )


if __name__ == "__main__":
    main(tyro.cli(Args))
