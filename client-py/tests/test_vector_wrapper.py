"""EsaVectorWrapper (one batched critic call per step, AsyncVectorEnv-safe) and the
cleanrl-style SAC and PPO examples with ESA, smoke-tested on a tiny budget."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

from esa_client import EsaConfig
from esa_client.vector_wrapper import EsaVectorWrapper

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _counting_critic(calls: list[int]) -> Any:
    def q_fn(obs: np.ndarray, actions: np.ndarray) -> np.ndarray:
        assert len(obs) == len(actions)
        calls.append(len(actions))
        return -np.sum((actions - 0.5) ** 2, axis=-1)

    return q_fn


@pytest.mark.parametrize("mode", ["sync", "async"])
def test_one_critic_call_per_step_for_all_envs(mode: str) -> None:
    calls: list[int] = []
    envs = gym.make_vec("Pendulum-v1", num_envs=3, vectorization_mode=mode)
    wrapped = EsaVectorWrapper(envs, _counting_critic(calls), esa=EsaConfig())
    try:
        wrapped.reset(seed=0)
        for _ in range(30):
            _, _, _, _, info = wrapped.step(np.zeros((3, 1), np.float32))
        # Paired response: the probes and the applied actions of all 3 envs in one call.
        assert calls == [6] * 30
        assert info["esa_action"].shape == (3, 1)
        assert np.all(info["esa_action"] > 0), "the shift moves toward the critic's best"
    finally:
        wrapped.close()


def test_unpaired_and_next_step_autoreset_start_new_episodes() -> None:
    calls: list[int] = []
    envs = gym.make_vec(
        "Pendulum-v1",
        num_envs=2,
        vectorization_mode="sync",
        wrappers=[lambda env: gym.wrappers.TimeLimit(env.unwrapped, max_episode_steps=5)],
    )
    wrapped = EsaVectorWrapper(
        envs, _counting_critic(calls), esa=EsaConfig(paired_response=False), action_scale=0.5
    )
    try:
        wrapped.reset(seed=0)
        starts = []
        for _ in range(7):
            starts.append(wrapped._starts.copy())
            wrapped.step(np.zeros((2, 1), np.float32))
        assert calls == [2] * 7
        # Step 5 ends the episode, step 6 is the reset step (action ignored), step 7 starts.
        assert [bool(s[0]) for s in starts] == [True, False, False, False, False, True, True]
    finally:
        wrapped.close()


def test_rejects_discrete_actions() -> None:
    envs = gym.make_vec("CartPole-v1", num_envs=2, vectorization_mode="sync")
    with pytest.raises(ValueError, match="Box"):
        EsaVectorWrapper(envs, _counting_critic([]))
    envs.close()


def _example(name: str) -> ModuleType:
    spec = importlib.util.spec_from_file_location(name, EXAMPLES / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses resolve the module's annotations through it
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("name", ["cleanrl_sac_esa", "cleanrl_ppo_esa"])
@pytest.mark.parametrize("esa", [True, False])
def test_cleanrl_examples_run_a_tiny_budget(name: str, esa: bool) -> None:
    pytest.importorskip("torch")
    module = _example(name)
    argv = ["--ci"] if esa else ["--ci", "--no-esa"]
    result = module.main(module.parse_args(argv))
    assert result["steps"] > 0
    assert result["episodes"] >= 1
    assert np.isfinite(result["mean_return_last_10"])
