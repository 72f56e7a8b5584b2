"""RLlib scaling: sampled env steps per second of PPO and SAC with 1 to 8 env runners.

For each algorithm (RLlib's PPO and SAC, new API stack, torch) and each number of env
runners N (1, 2, 4, 8, capped by ``--max-runners``), four setups train on Pendulum-v1
with one env per runner (``num_envs_per_env_runner=1``): ``plain`` (RLlib alone),
``in-runner`` (``with_esa``'s default: each runner keeps its sessions in its own process),
``shared`` (one esa-server over TCP, ``EsaService(address=...)``) and ``zenoh`` (two
esa-server shards over Zenoh, ``EsaService(zenoh=..., shards=2)``). A row builds the
algorithm, runs ``warmup`` untimed iterations, then ``iterations`` timed ones; its rate is
the growth of ``env_runners/num_env_steps_sampled_lifetime`` over the timed iterations'
wall-clock. The rate is over whole iterations (sampling and learning), what a user sees.

Pendulum-v1, not InvertedPendulum-v5: numpy only (no MuJoCo), never terminates early
(fixed 200-step episodes, so every row samples the same episode structure), the env of the
RLlib guide and tests, and cheap per step, so ESA's per-step cost weighs as much as it can.

The in-runner setup runs with each ESA config of ``--configs``: ``default`` is what
``with_esa`` ships (``EsaConfig.ppo()`` / ``EsaConfig.off_policy()``, ``budget=1,000,000``:
a long run, so the fade barely moves during the bench), whose gate keeps ESA off until the
critic is good (on a fresh run, usually all of the bench); ``ungated`` is the same with
``gate=None`` (PPO also ``fade=None``): ESA acts at every step once a critic exists, what it
costs while it acts and the load a server sees. The shared and zenoh setups run
``--server-configs`` (ungated): with the default's gate closed no runner opens a session.
Each ESA row records ``env_runners/esa/active`` (share of steps ESA acted on) and so the
session-steps per second it asked of its service (env steps x active share, one session per
runner). The shared server runs with ``--metrics-listen``: its ``esa_requests_total`` over
the timed window is recorded too. PPO's and SAC's settings are RLlib's defaults but for the
batch sizes and SAC's ``rollout_fragment_length`` (``Args``), chosen so that sampling, not
learning, takes most of an iteration.

The setups of one (algorithm, N) run back to back, in reverse order every other repeat.
Ray gets N logical CPUs, one per runner (``num_cpus_per_env_runner=1``): with more runners
than cores the runners share the cores, and the rows measure that contention.

Usage::

    python bench/python/rllib_scaling.py [--max-runners 8] [--quick]
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import re
import subprocess
import tempfile
import time
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import ray
import torch as th
import tyro
from esa_client import EsaClient, EsaConfig
from esa_client.compare.execution import start_local_ray
from esa_client.rllib import EsaService, with_esa
from ray.rllib.algorithms.ppo import PPOConfig
from ray.rllib.algorithms.sac import SACConfig
from ray.rllib.utils.metrics import ENV_RUNNER_RESULTS, NUM_ENV_STEPS_SAMPLED_LIFETIME

from servers import server_binary

ENV = "Pendulum-v1"
ALGOS = ("PPO", "SAC")
SETUPS = ("plain", "in-runner", "shared", "zenoh")
SHARDS = 2
"""Zenoh shards of the ``zenoh`` setup."""
BUDGET = 1_000_000
"""``with_esa``'s budget: a long run's, so the default's fade barely moves in the bench."""
ESA_CONFIGS = {
    "default": {"PPO": EsaConfig.ppo(), "SAC": EsaConfig.off_policy()},
    "ungated": {"PPO": EsaConfig.ppo(gate=None, fade=None), "SAC": EsaConfig.off_policy(gate=None)},
}
"""ESA config name -> per algorithm, the ``esa=`` of ``with_esa``."""


@dataclass
class Args:
    """Sampled env steps per second of RLlib PPO and SAC, with and without ESA, 1 to 8 runners."""

    max_runners: int = 8
    """Largest number of env runners (of 1, 2, 4, 8)."""
    runners: str = "1,2,4,8"
    """Numbers of env runners, comma-separated (those above ``max_runners`` are dropped)."""
    algos: str = ",".join(ALGOS)
    """Algorithms, comma-separated."""
    setups: str = ",".join(SETUPS)
    """Setups, comma-separated: plain, in-runner, shared, zenoh."""
    configs: str = "default,ungated"
    """ESA configs of the in-runner setup, comma-separated: default, ungated."""
    server_configs: str = "ungated"
    """ESA configs of the shared and zenoh setups. Not the default by default: while its gate
    is closed no runner opens a session, so it would time the in-runner default again."""
    warmup: int = 2
    """Untimed iterations per row (a SAC iteration before learning starts samples only)."""
    iterations: int = 4
    """Timed iterations per row."""
    repeats: int = 1
    """Times each (algorithm, N) runs all its setups."""
    ppo_batch: int = 2000
    """PPO's ``train_batch_size_per_learner``: env steps per iteration, all runners."""
    ppo_epochs: int = 4
    """PPO's ``num_epochs`` (minibatches of 250)."""
    sac_steps: int = 1000
    """SAC's ``min_sample_timesteps_per_iteration``."""
    sac_learning_starts: int = 1000
    """SAC's ``num_steps_sampled_before_learning_starts`` (within the warm-up)."""
    sac_fragment: int = 50
    """SAC's ``rollout_fragment_length``: each training step samples this many env steps per
    runner, then makes one gradient update (RLlib's default, "auto", is 1: an update and a
    weight sync per env step, some 3 env steps/s on a 2-core host, too few to time ESA's
    per-step work)."""
    quick: bool = False
    """Smoke test: 1 and 2 runners, 1 warm-up and 1 timed iteration, the default config
    only, smaller batches."""
    seed: int = 0
    """Seed of the runs."""
    out: str = "bench/results/rllib_scaling.json"
    """JSON of the rows."""


def quick(args: Args) -> Args:
    """The quick mode's settings."""
    return dataclasses.replace(
        args,
        max_runners=min(args.max_runners, 2),
        configs="ungated",
        server_configs="ungated",
        warmup=1,
        iterations=1,
        ppo_batch=1000,
        ppo_epochs=1,
        sac_steps=200,
        sac_learning_starts=200,
    )


def build_config(algo: str, runners: int, args: Args) -> Any:
    """The plain RLlib config of ``algo`` with ``runners`` env runners of one env each."""
    common: dict[str, Any] = dict(
        num_env_runners=runners, num_envs_per_env_runner=1, num_cpus_per_env_runner=1
    )
    if algo == "PPO":
        return (
            PPOConfig()
            .environment(ENV)
            .env_runners(**common)
            .training(
                train_batch_size_per_learner=args.ppo_batch,
                minibatch_size=250,
                num_epochs=args.ppo_epochs,
            )
            .debugging(seed=args.seed)
        )
    return (
        SACConfig()
        .environment(ENV)
        .env_runners(**common, rollout_fragment_length=args.sac_fragment)
        .training(num_steps_sampled_before_learning_starts=args.sac_learning_starts)
        .reporting(min_sample_timesteps_per_iteration=args.sac_steps, min_time_s_per_iteration=0)
        .debugging(seed=args.seed)
    )


@contextlib.contextmanager
def shared_server() -> Iterator[tuple[str, str]]:
    """One esa-server over TCP on loopback, with metrics; yields (address, metrics URL)."""
    process = subprocess.Popen(
        [
            server_binary(),
            "--listen",
            "127.0.0.1:0",
            "--metrics-listen",
            "127.0.0.1:0",
            "--session-ttl",
            "0",
            "--parent-pid",
            str(os.getpid()),
        ],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        metrics = address = None
        assert process.stdout is not None
        for line in process.stdout:
            if line.startswith("metrics on "):
                metrics = line.split()[-1]
            if line.startswith("listening on "):
                address = line.split()[-1]
                break
        if address is None or metrics is None:
            raise RuntimeError(f"esa-server did not start (exit {process.poll()})")
        if not metrics.endswith("/metrics"):
            metrics = metrics.rstrip("/") + "/metrics"
        yield address, metrics
    finally:
        process.terminate()
        try:
            process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def requests_total(url: str) -> float:
    """The server's ``esa_requests_total`` over every RPC and code."""
    text = urllib.request.urlopen(url, timeout=5).read().decode()
    pattern = re.compile(r"^esa_requests_total\{[^}]*\} ([0-9.e+]+)$", re.MULTILINE)
    return sum(float(value) for value in pattern.findall(text))


@contextlib.contextmanager
def service(setup: str) -> Iterator[tuple[EsaService | None, str | None]]:
    """The setup's ``EsaService`` (None: plain RLlib) and the shared server's metrics URL."""
    if setup == "plain":
        yield None, None
    elif setup == "in-runner":
        yield EsaService(), None
    elif setup == "shared":
        with shared_server() as (address, metrics):
            yield EsaService(address=address), metrics
    elif setup == "zenoh":
        with (
            EsaClient.spawn(server_binary(), transport="zenoh", shards=SHARDS) as shards,
            tempfile.TemporaryDirectory() as folder,
        ):
            token = Path(folder) / "token"
            token.write_text(shards.servers[0].token or "")
            locators = shards.address.split(",")
            yield EsaService(zenoh=locators, shards=SHARDS, token_file=str(token)), None
    else:
        raise ValueError(f"expected a setup of {SETUPS}, got {setup!r}")


def sampled(result: dict) -> int:
    """The env steps sampled so far, all runners."""
    return int(result[ENV_RUNNER_RESULTS][NUM_ENV_STEPS_SAMPLED_LIFETIME])


def measure(algo: str, runners: int, setup: str, esa: str | None, args: Args) -> dict:
    """Builds one row's algorithm, warms it up, times ``iterations`` iterations; the row."""
    with service(setup) as (esa_service, metrics_url):
        config = build_config(algo, runners, args)
        if esa_service is not None:
            assert esa is not None
            config = with_esa(
                config, esa=ESA_CONFIGS[esa][algo], service=esa_service, budget=BUDGET
            )
        started = time.perf_counter()
        trainer = config.build_algo()
        build_s = time.perf_counter() - started
        try:
            result = {}
            for _ in range(args.warmup):
                result = trainer.train()
            steps_before = sampled(result) if result else 0
            requests_before = requests_total(metrics_url) if metrics_url else None
            load_before = os.getloadavg()[0]
            active = []
            started = time.perf_counter()
            for _ in range(args.iterations):
                result = trainer.train()
                active.append(result[ENV_RUNNER_RESULTS].get("esa/active"))
            seconds = time.perf_counter() - started
            requests_after = requests_total(metrics_url) if metrics_url else None
        finally:
            trainer.stop()
    steps = sampled(result) - steps_before
    known = [a for a in active if a is not None]
    active_share = sum(known) / len(known) if known else None
    row: dict[str, Any] = {
        "algo": algo,
        "runners": runners,
        "setup": setup,
        "esa": esa,
        "env_steps": steps,
        "seconds": seconds,
        "env_steps_per_s": steps / seconds,
        "build_s": build_s,
        "esa_active": active_share,
        # One session per runner: an env step ESA acted on is one session-step.
        "session_steps_per_s": None if active_share is None else steps * active_share / seconds,
        "server_requests_per_s": None
        if requests_before is None or requests_after is None
        else (requests_after - requests_before) / seconds,
        "loadavg_1m_before": load_before,
        "loadavg_1m_after": os.getloadavg()[0],
    }
    return row


def host() -> dict:
    """The host's cores, memory and load."""
    mem_kib = next(
        int(line.split()[1]) for line in open("/proc/meminfo") if line.startswith("MemTotal:")
    )
    return {"cores": os.cpu_count(), "ram_gib": mem_kib / 2**20, "loadavg": os.getloadavg()}


def main() -> None:
    """Times every (algorithm, runners, setup, ESA config) row and writes the JSON."""
    args = tyro.cli(Args)
    if args.quick:
        args = quick(args)
    if args.warmup < 1 or args.iterations < 1:
        raise SystemExit("expected --warmup and --iterations >= 1")
    th.set_num_threads(1)
    os.environ["ESA_SERVER_BIN"] = server_binary()
    runner_counts = [n for n in map(int, args.runners.split(",")) if n <= args.max_runners]
    setups = args.setups.split(",")
    configs = {"in-runner": args.configs.split(","), "plain": [None]}
    server_configs = args.server_configs.split(",")
    rows = []
    host_start = host()
    started = time.time()
    start_local_ray(num_cpus=max(runner_counts))
    try:
        for algo in args.algos.split(","):
            for runners in runner_counts:
                for repeat in range(args.repeats):
                    runs = [
                        (setup, esa)
                        for setup in setups
                        for esa in configs.get(setup, server_configs)
                    ]
                    for setup, esa in runs[::-1] if repeat % 2 else runs:
                        row = measure(algo, runners, setup, esa, args)
                        row["repeat"] = repeat
                        rows.append(row)
                        print(
                            f"{algo} {runners} runner(s) {setup:<9} {esa or '-':<8} "
                            f"{row['env_steps_per_s']:8.1f} env steps/s "
                            f"({row['env_steps']} in {row['seconds']:.1f} s, build "
                            f"{row['build_s']:.1f} s, ESA active {row['esa_active']})",
                            flush=True,
                        )
    finally:
        ray.shutdown()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    result = {
        "args": dataclasses.asdict(args),
        "env": ENV,
        "shards": SHARDS,
        "budget": BUDGET,
        "host_start": host_start,
        "host_end": host(),
        "wall_s": time.time() - started,
        "rows": rows,
    }
    out.write_text(json.dumps(result, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
