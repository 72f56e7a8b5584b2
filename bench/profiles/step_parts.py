"""Where ESAPPO's extra wall-clock goes, timed inside real training runs (not micro-benchmarks).

A step's small operations cost two to three times more inside training than in a loop of
their own (the env and PPO's update evict them from the caches between steps), so this
times them where they run: PPO, ESAPPO with its gate never open (``EsaConfig(gate=1.0)``:
the head is fitted and gated every rollout, no ESA step) and the shipped ESAPPO, alternating,
``--repeats`` times, after one short untimed run of each. ``--agents`` adds two controls:
``PPO again`` (a second PPO in the alternation: the ratio an A/A pair gives) and ``ESAPPO
unfitted`` (the head is never fitted or gated, so the gate stays closed: ESAPPO's hook and
nothing else). Timers wrap SB3's ``collect_rollouts`` and ``train``, the policy's
forward pass (``ESAPPO._esa_policy_step`` in ESAPPO), ``ESAPPO._step_features`` (the head's input),
``EsaRuntime.step_head`` (the whole ESA step: one native call in-process; elsewhere the
head's step inputs, ``EsaRuntime.step``'s probe and report, also timed, and the executed
action) and ``fit`` where the trainer runs it (the head-fit worker's fits are not timed: with
a worker serving, the row is 0 but for the fits made before it started).

Settings as ``run_one.py``: InvertedPendulum-v5, 1 env, SB3's default PPO, 12,288 steps,
torch on one thread, the in-process engine (``--engine sidecar`` for the sidecar).

Usage::

    python bench/profiles/step_parts.py [--repeats 3] [--engine inprocess] \
        [--agents "PPO,PPO again,ESAPPO gate closed,ESAPPO unfitted,ESAPPO"] > step_parts.md
"""

from __future__ import annotations

import contextlib
import functools
import sys
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch as th
import tyro
from esa_client.common.runtime import EsaRuntime
from esa_client.sb3 import ESAPPO, EsaConfig
from esa_client.sb3 import ppo as esappo_module
from esa_client.session import SessionBatch
from run_one import EngineName
from stable_baselines3 import PPO
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.on_policy_algorithm import OnPolicyAlgorithm

SECONDS: dict[str, float] = defaultdict(float)
STEP_HEAD = "the ESA step (EsaRuntime.step_head)"
AGENTS = ("PPO", "PPO again", "ESAPPO gate closed", "ESAPPO unfitted", "ESAPPO")
WARMUP_STEPS = 2048
"""One rollout and update: a process's first run pays one-time costs (torch's first kernels,
MuJoCo's model) that would otherwise fall on the first timed run, PPO's."""


def timed(label: str, function: Callable[..., Any]) -> Callable[..., Any]:
    """``function``, adding its wall seconds to ``SECONDS[label]``."""

    @functools.wraps(function)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        start = time.perf_counter()
        try:
            return function(*args, **kwargs)
        finally:
            SECONDS[label] += time.perf_counter() - start

    return wrapper


@contextlib.contextmanager
def timers() -> Iterator[None]:
    """Wraps the methods named in the module doc for the block."""
    patched = [
        (OnPolicyAlgorithm, "collect_rollouts", "collect_rollouts"),
        (PPO, "train", "PPO train"),
        (ESAPPO, "train", "ESAPPO train (PPO's + the head's fit and gate)"),
        (ESAPPO, "_step_features", "head features (_step_features)"),
        # ESAPPO's collect_rollouts calls this in the place of the policy's forward pass.
        (ESAPPO, "_esa_policy_step", "policy forward (with ESA's hook)"),
        (EsaRuntime, "step_head", STEP_HEAD),
        (EsaRuntime, "step", "  of which probe + report, where not fused (EsaRuntime.step)"),
        (SessionBatch, "probe_applied", "  of which the sidecar's round trip (probe_applied)"),
    ]
    originals = [(cls, name, getattr(cls, name)) for cls, name, _ in patched]
    fit = esappo_module.fit
    for cls, name, label in patched:
        setattr(cls, name, timed(label, getattr(cls, name)))
    esappo_module.fit = timed("head fit", fit)
    try:
        yield
    finally:
        for cls, name, original in originals:
            setattr(cls, name, original)
        esappo_module.fit = fit


def run(agent: str, engine: str, steps: int) -> tuple[float, dict[str, float], int]:
    """One training: learn()'s seconds, the timers' seconds, ESA's active steps."""
    env = make_vec_env("InvertedPendulum-v5", n_envs=1, seed=0)
    common: dict[str, Any] = dict(n_steps=2048, seed=0, device="cpu", verbose=0)
    if agent in ("PPO", "PPO again"):
        model: PPO = PPO("MlpPolicy", env, **common)
        # PPO's forward is the policy's method; timed per instance like the hook.
        model.policy.forward = timed("policy forward (with ESA's hook)", model.policy.forward)  # type: ignore[method-assign]
    else:
        closed = agent in ("ESAPPO gate closed", "ESAPPO unfitted")
        esa = EsaConfig(gate=1.0) if closed else EsaConfig()
        model = ESAPPO("MlpPolicy", env, esa=esa, esa_engine=engine, **common)
        if agent == "ESAPPO unfitted":
            model._update_esa_head = lambda: None  # type: ignore[method-assign]
            model._finish_esa_head_fit = lambda pending: None  # type: ignore[method-assign]
    active = 0
    if isinstance(model, ESAPPO):
        collect = model.collect_rollouts

        def counting_collect(*args: Any, **kwargs: Any) -> bool:
            nonlocal active
            was_active = model._esa_active
            result = collect(*args, **kwargs)
            active += model.n_steps if was_active else 0
            return result

        model.collect_rollouts = counting_collect  # type: ignore[method-assign]
    SECONDS.clear()
    start = time.perf_counter()
    model.learn(steps)
    total = time.perf_counter() - start
    if isinstance(model, ESAPPO):
        model.esa_close()
    return total, dict(SECONDS), active


@dataclass
class Args:
    """Where ESAPPO's extra wall-clock goes, timed inside real training runs."""

    repeats: int = 3
    """Timed runs per agent, alternating."""
    steps: int = 12_288
    """Training steps per run."""
    engine: EngineName = "inprocess"
    """ESAPPO's engine."""
    agents: str = "PPO,ESAPPO gate closed,ESAPPO"
    """Agents to time, comma-separated, PPO first."""


def main(args: Args) -> None:
    """Prints a Markdown table of medians over the repeats."""
    agents = tuple(args.agents.split(","))
    if agents[0] != "PPO" or not set(agents) <= set(AGENTS):
        print(
            f"error: --agents: expected PPO first, then some of {AGENTS}, got {agents}",
            file=sys.stderr,
        )
        sys.exit(2)
    th.set_num_threads(1)
    results: dict[str, list[tuple[float, dict[str, float], int]]] = defaultdict(list)
    with timers():
        for agent in agents:
            run(agent, args.engine, WARMUP_STEPS)
        for _ in range(args.repeats):
            for agent in agents:
                results[agent].append(run(agent, args.engine, args.steps))
    labels = sorted({label for runs in results.values() for _, parts, _ in runs for label in parts})
    print(f"engine: {args.engine}; {args.steps} steps, 1 env; medians of {args.repeats} runs\n")
    print("| seconds | " + " | ".join(agents) + " |")
    print("|---|" + "---:|" * len(agents))
    rows = [("learn()", lambda r: r[0])] + [
        (label, lambda r, label=label: r[1].get(label, 0.0)) for label in labels
    ]
    for name, value in rows:
        cells = [f"{np.median([value(r) for r in results[a]]):.3f}" for a in agents]
        print(f"| {name} | " + " | ".join(cells) + " |")
    plain = np.asarray([r[0] for r in results["PPO"]])
    for agent in agents[1:]:
        pairs = np.asarray([r[0] for r in results[agent]]) / plain
        print(f"\n{agent} / PPO: {np.median(pairs):.3f} (pairs {pairs.round(3).tolist()})", end="")
    if "ESAPPO" not in results:
        print()
        return
    active = int(np.median([r[2] for r in results["ESAPPO"]]))
    print(f"\n\nESAPPO's ESA steps (rollouts with the gate open): {active}")
    per_step_labels = ("head features (_step_features)", STEP_HEAD)
    per_step = {
        label: np.median([r[1].get(label, 0.0) for r in results["ESAPPO"]]) / max(active, 1) * 1e6
        for label in per_step_labels
    }
    for label, micros in per_step.items():
        print(f"- {label}: {micros:.1f} us per ESA step")


if __name__ == "__main__":
    main(tyro.cli(Args))
