"""Training wall-clock with and without ESA: PPO, SAC and TD3 against their ESA drop-ins.

Each pair trains for the same number of steps on InvertedPendulum-v5, the same seed
and hyperparameters, torch on one thread, with one env by default (SB3's default, how
most users run it; ``--n-envs 1,8`` adds 8 envs in a ``DummyVecEnv``), PPO with SB3's
default 2048-step rollouts. Every ESA agent runs once per
engine: ``inprocess`` (``esa_client=None``: esa-core in the trainer's process) and
``sidecar`` (``esa_client="spawn"``: a private esa-server on a Unix socket, called through
the Rust client of ``esa_client._native``). Only ``learn()`` is timed; for the ESA agents
that includes creating the sessions, the round trips, the critic evaluations and ESAPPO's
advantage head, not spawning the server (the model does that when it is built).
The agents run family by family, and a family's plain agent and its ESA agents train side
by side: one thread each, of which one at a time runs while the others wait, handing the
turn to the next every ``slice_s`` seconds of its wall-clock (at a step's end, from a
callback), round-robin. An agent's time is the sum of its turns, so a drift of the host's
speed (this VM's PPO alone varies 15-30 % between runs minutes apart) falls on every agent
of the family alike instead of on whichever ran during it; every other repeat takes the
turns in reverse order. A warm-up of ``warmup_runs`` short untimed runs of every agent
goes first. SAC's and TD3's families run ``repeats`` times; PPO's, whose runs take
seconds, ``ppo_repeats`` times.

The ESA agents run each family's shipped default (``EsaConfig.ppo()`` for ESAPPO,
``EsaConfig.off_policy()`` for ESASAC and ESATD3) and, to price ESA when it is on at every
step, the same with ``gate=None`` (and, for ESAPPO, ``fade=None``): the gate keeps ESA off
while the critic is poor and the fade turns it off halfway, so the default's cost depends
on the run. The controls are priced too: the placebo (ESA's sessions, a random direction)
and the gradient control (autograd in the trainer, no engine, so it runs once, on no
engine).

To tell the service's share from the algorithm's, the ESA agents' time is also split
by wrapping methods with timers: the round trips (``SessionBatch.probe_applied``, which
carries the deferred report too, and ``.flush``; the in-process step is one
``InProcessBatch.step_closed_form`` call: probe, the quadratic head's closed form, report; a
step sent ahead through the native client is its send and the reading of its answer a step
later), the whole ESA step (``EsaRuntime.step``: round trips plus critic evaluations) and
ESAPPO's critic: its gate and its fit.

Usage::

    python bench/python/training_overhead.py [--ppo-steps 12288] [--sac-steps 8000] [--n-envs 1]
        [--agents "ESAPPO,ESATD3 qgrad"] [--engines inprocess]
"""

from __future__ import annotations

import dataclasses
import json
import os
import threading
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch as th
import tyro
from esa_client import SessionBatch
from esa_client.common.runtime import EsaRuntime
from esa_client.sb3 import ESAPPO, ESASAC, ESATD3, EsaConfig
from esa_client.transports.grpc import GrpcStepBatch
from esa_client.transports.in_process import InProcessBatch
from stable_baselines3 import PPO, SAC, TD3
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env

from servers import server_binary


@dataclass(frozen=True)
class Agent:
    """An ESA agent of the bench.

    Attributes:
        plain: Its algorithm without ESA (``PPO``, ``SAC`` or ``TD3``).
        esa: Its ``esa=`` (None: the family's shipped default).
        options: Its other ESA keyword arguments (the control).
        engine_free: True for the gradient controls: no session, so no engine to compare.
    """

    plain: str
    esa: EsaConfig | None = None
    options: tuple[tuple[str, object], ...] = ()
    engine_free: bool = False


GRADIENT = (("esa_control", "gradient"),)
PLACEBO = (("esa_control", "placebo"),)
AGENTS = {
    "ESAPPO": Agent("PPO"),
    "ESAPPO ungated": Agent("PPO", EsaConfig.ppo(gate=None, fade=None)),
    "ESAPPO placebo": Agent("PPO", options=PLACEBO),
    "ESAPPO qgrad": Agent("PPO", options=GRADIENT, engine_free=True),
    "ESASAC": Agent("SAC"),
    "ESASAC ungated": Agent("SAC", EsaConfig.off_policy(gate=None)),
    "ESASAC qgrad": Agent("SAC", options=GRADIENT, engine_free=True),
    "ESATD3": Agent("TD3"),
    "ESATD3 qgrad": Agent("TD3", options=GRADIENT, engine_free=True),
}
"""ESA agent name -> what it runs."""
PLAIN = {"PPO": PPO, "SAC": SAC, "TD3": TD3}
DROP_IN = {"PPO": ESAPPO, "SAC": ESASAC, "TD3": ESATD3}
ENGINE_FREE = "none"
"""The engine column of the engine-free agents."""
ESA_CLIENT = {"inprocess": None, "sidecar": "spawn"}
"""Engine column -> the drop-in's ``esa_client``."""


@dataclass
class Args:
    """Training wall-clock with and without ESA, each agent against its ESA drop-in."""

    env_id: str = "InvertedPendulum-v5"
    """Gymnasium id of the env."""
    n_envs: str = "1"
    """Numbers of training envs, comma-separated."""
    ppo_steps: int = 12_288
    """Training steps of PPO and ESAPPO."""
    ppo_n_steps: int = 2048
    """PPO rollout length per env."""
    sac_steps: int = 8_000
    """Training steps of the off-policy agents."""
    sac_learning_starts: int = 800
    """Random-action steps of the off-policy agents before they learn."""
    repeats: int = 2
    """Timed pairs per off-policy agent (SAC, TD3), engine and number of envs."""
    ppo_repeats: int = 4
    """Timed pairs per on-policy agent (PPO), engine and number of envs: an even number, so
    the turns are taken forward and reversed alike."""
    slice_s: float = 0.25
    """Wall-clock seconds an agent trains before it hands the turn to the next agent of its
    family (the turn passes at the end of an env step, so a PPO update finishes first)."""
    warmup_runs: int = 1
    """Short untimed runs of every agent first: a process's first training pays one-time
    costs (torch's first kernels, MuJoCo's model, the server binary read from disk) that
    would otherwise fall on the first timed run, PPO's, and favour the ESA agent."""
    agents: str = ",".join(AGENTS)
    """ESA agents to time, comma-separated."""
    engines: str = "inprocess,sidecar"
    """ESA engines to time, comma-separated."""
    seed: int = 0
    """Seed of the agents and the envs."""
    out: str = "bench/results/training.json"
    """JSON of the timings."""


WARMUP_GRADIENT_STEPS = 200
"""SAC's and TD3's gradient steps in a warm-up run, after ``sac_learning_starts``."""

# (class, method, bucket): where the ESA agents' extra time goes.
TIMED = [
    (SessionBatch, "probe_applied", "round_trips"),
    (SessionBatch, "flush", "round_trips"),
    (InProcessBatch, "step_closed_form", "round_trips"),
    # A step sent ahead through the native client's stream (a linear critic, or the critic's
    # values at probes computed here): the send, and reading the answer one step later
    # (mostly arrived by then).
    (GrpcStepBatch, "send_step_linear", "round_trips"),
    (GrpcStepBatch, "send_step", "round_trips"),
    (GrpcStepBatch, "receive_step", "round_trips"),
    (EsaRuntime, "step", "esa_step"),
    (ESAPPO, "_check_gate", "critic_fit"),
    (ESAPPO, "_fit_critic", "critic_fit"),
]


@contextmanager
def timed_methods() -> Iterator[dict[int, dict[str, float]]]:
    """Wraps the ``TIMED`` methods with timers; yields the seconds per thread and bucket.

    The agents of a family train on threads of their own, so each thread's seconds are
    one agent's.
    """
    seconds: dict[int, dict[str, float]] = defaultdict(lambda: defaultdict(float))
    # Timed calls running per thread and bucket: a call inside another of its bucket counts once.
    running: dict[tuple[int, str], int] = defaultdict(int)

    def wrap(method: Callable, bucket: str) -> Callable:
        def timed(*args, **kwargs):
            key = (threading.get_ident(), bucket)
            start = time.perf_counter()
            running[key] += 1
            try:
                return method(*args, **kwargs)
            finally:
                running[key] -= 1
                if not running[key]:
                    seconds[key[0]][bucket] += time.perf_counter() - start

        return timed

    originals = [(cls, name, getattr(cls, name)) for cls, name, _ in TIMED]
    for (cls, name, bucket), (_, _, method) in zip(TIMED, originals, strict=True):
        setattr(cls, name, wrap(method, bucket))
    try:
        yield seconds
    finally:
        for cls, name, method in originals:
            setattr(cls, name, method)


class Turns:
    """Lets one of several threads run at a time, round-robin, and sums each one's turns."""

    def __init__(self, order: list[int]) -> None:
        """Starts with ``order[0]``'s turn; the turns go in ``order``."""
        self._order = order
        self._waiting = list(order)
        self._turn = order[0]
        self._changed = threading.Condition()
        self.seconds = dict.fromkeys(order, 0.0)
        self._since = 0.0

    def take(self, index: int) -> None:
        """Blocks until it is ``index``'s turn, then starts its clock."""
        with self._changed:
            self._changed.wait_for(lambda: self._turn == index)
        self._since = time.perf_counter()

    def give(self, index: int, done: bool = False) -> None:
        """Stops ``index``'s clock and hands the turn to the next thread still training."""
        self.seconds[index] += time.perf_counter() - self._since
        with self._changed:
            if done:
                self._waiting.remove(index)
            # _waiting keeps the order of the turns: the next is the first after ``index``,
            # else the first of the round.
            if self._waiting:
                position = self._order.index(index)
                later = [i for i in self._waiting if self._order.index(i) > position]
                self._turn = (later or self._waiting)[0]
            self._changed.notify_all()

    def elapsed(self) -> float:
        """Seconds since the running thread's turn began."""
        return time.perf_counter() - self._since


class TakeTurns(BaseCallback):
    """Hands the turn to the next agent once this one has trained ``slice_s`` seconds."""

    def __init__(self, turns: Turns, index: int, slice_s: float) -> None:
        """Takes turns in ``turns`` as thread ``index``, each turn ``slice_s`` seconds long."""
        super().__init__()
        self.turns, self.index, self.slice_s = turns, index, slice_s

    def _on_step(self) -> bool:
        if self.turns.elapsed() >= self.slice_s:
            self.turns.give(self.index)
            self.turns.take(self.index)
        return True


def agent_name(agent: str, engine: str) -> str:
    """The name of an ESA agent on one engine, as the results and BENCHMARKS.md show it."""
    return f"{agent} [{engine}]"


def build(name: str, n_envs: int, args: Args, engine: str | None) -> tuple[BaseAlgorithm, int]:
    """Builds agent ``name`` (``PPO``, ``SAC``, ``TD3`` or a key of ``AGENTS``) and its steps.

    Args:
        name: The agent.
        n_envs: How many envs.
        args: The benchmark settings.
        engine: The ESA agent's engine (a key of ``ESA_CLIENT``) or ``ENGINE_FREE`` (None for
            the plain ones).

    Returns:
        The model, on its own envs, and the steps it trains.
    """
    env = make_vec_env(args.env_id, n_envs=n_envs, seed=args.seed)
    common: dict = dict(seed=args.seed, device="cpu", verbose=0)
    if name in PLAIN:
        family, cls = name, PLAIN[name]
    else:
        agent = AGENTS[name]
        family, cls = agent.plain, DROP_IN[agent.plain]
        common.update(agent.options)
        if engine not in (None, ENGINE_FREE):
            common["esa_client"] = ESA_CLIENT[engine]
        if agent.esa is not None:
            common["esa"] = agent.esa
    if family == "PPO":
        model = cls("MlpPolicy", env, n_steps=args.ppo_n_steps, batch_size=64, **common)
        return model, args.ppo_steps
    model = cls("MlpPolicy", env, learning_starts=args.sac_learning_starts, **common)
    return model, args.sac_steps


def train_family(
    block: list[tuple[str, str, str | None]], n_envs: int, args: Args, reverse: bool
) -> dict[str, tuple[float, dict[str, float]]]:
    """Trains a family's agents side by side, taking turns, and times each one's ``learn()``.

    Args:
        block: The family's agents as (name, agent, engine), its plain agent first.
        n_envs: How many envs each agent trains on.
        args: The benchmark settings.
        reverse: Take the turns in reverse order.

    Returns:
        Per agent name, the wall-clock seconds of its turns and the seconds spent in each
        ``TIMED`` bucket.
    """
    models = [build(agent, n_envs, args, engine) for _, agent, engine in block]
    order = list(range(len(block)))
    turns = Turns(order[::-1] if reverse else order)
    idents: dict[int, int] = {}
    failures: list[BaseException] = []

    def train(index: int) -> None:
        model, steps = models[index]
        idents[index] = threading.get_ident()
        turns.take(index)
        try:
            model.learn(steps, callback=TakeTurns(turns, index, args.slice_s))
        except BaseException as err:  # re-raised in the main thread, after the others end
            failures.append(err)
        finally:
            turns.give(index, done=True)

    with timed_methods() as buckets:
        threads = [threading.Thread(target=train, args=(i,)) for i in order]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
    for model, _ in models:
        if isinstance(model, (ESAPPO, ESASAC, ESATD3)):
            model.esa_close()
        model.get_env().close()
    if failures:
        raise failures[0]
    return {
        name: (turns.seconds[i], dict(buckets.get(idents[i], {})))
        for i, (name, _, _) in enumerate(block)
    }


def main() -> None:
    """Times every family's agents side by side, repeatedly per env count, and writes the ratios."""
    args = tyro.cli(Args)
    if args.slice_s <= 0:
        raise SystemExit(f"expected --slice-s > 0 (seconds per turn), got {args.slice_s}")
    out = Path(args.out)
    th.set_num_threads(1)
    # Without it every spawn would first ask cargo whether the binary is up to date.
    os.environ["ESA_SERVER_BIN"] = server_binary()
    rows = []
    agents = args.agents.split(",")
    engines = args.engines.split(",")
    # One block per family: its plain agent first, then its ESA agents on every engine.
    blocks: dict[str, list[tuple[str, str, str | None]]] = {
        plain: [(plain, plain, None)] for plain in sorted({AGENTS[a].plain for a in agents})
    }
    for a in agents:
        blocks[AGENTS[a].plain] += [
            (agent_name(a, e), a, e) for e in ([ENGINE_FREE] if AGENTS[a].engine_free else engines)
        ]
    runs = [run for block in blocks.values() for run in block]
    repeats_of = {plain: args.ppo_repeats if plain == "PPO" else args.repeats for plain in blocks}
    for n_envs in (int(n) for n in args.n_envs.split(",")):
        seconds: dict[str, list[float]] = {name: [] for name, _, _ in runs}
        buckets: dict[str, list[dict[str, float]]] = {name: [] for name, _, _ in runs}
        # One rollout and update for PPO, a few gradient steps for SAC and TD3.
        short = dataclasses.replace(
            args,
            ppo_steps=args.ppo_n_steps * n_envs,
            sac_steps=args.sac_learning_starts + WARMUP_GRADIENT_STEPS,
        )
        for _ in range(args.warmup_runs):
            for block in blocks.values():
                for name, (wall, _) in train_family(block, n_envs, short, False).items():
                    print(f"{n_envs} env(s) {name:<26} {wall:7.2f} s  (warm-up)", flush=True)
        for repeat in range(max(repeats_of.values())):
            for plain, block in blocks.items():
                if repeat >= repeats_of[plain]:
                    continue
                timed = train_family(block, n_envs, args, reverse=repeat % 2 == 1)
                for name, (wall, split) in timed.items():
                    seconds[name].append(wall)
                    buckets[name].append(split)
                    parts = ", ".join(f"{k} {v:.2f} s" for k, v in split.items())
                    print(f"{n_envs} env(s) {name:<26} {wall:7.2f} s  {parts}", flush=True)
        for esa, agent, engine in runs:
            if engine is None:
                continue
            plain = AGENTS[agent].plain
            ratios = np.asarray(seconds[esa]) / np.asarray(seconds[plain])
            rows.append(
                {
                    "plain": plain,
                    "esa": esa,
                    "engine": engine,
                    "n_envs": n_envs,
                    "steps": args.ppo_steps if plain == "PPO" else args.sac_steps,
                    "plain_seconds": seconds[plain],
                    "esa_seconds": seconds[esa],
                    "ratio_median": float(np.median(ratios)),
                    "ratios": ratios.tolist(),
                    "esa_buckets": buckets[esa],
                }
            )
            print(f"{n_envs} env(s) {esa}/{plain} ratio: {np.median(ratios):.3f} {ratios.round(3)}")
    out.parent.mkdir(parents=True, exist_ok=True)
    result = {"args": dataclasses.asdict(args), "rows": rows}
    out.write_text(json.dumps(result, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
