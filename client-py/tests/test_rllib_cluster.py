"""RLlib PPO with ESA on a real multi-node Ray cluster, a worker node lost mid-run.

``ray.cluster_utils.Cluster`` starts a head node and two worker nodes on this host, each its
own raylet and object store; the head has no CPU for env runners, each worker one, so the
two env runners run on different nodes. In each of three setups (sessions in each runner, one
shared esa-server over TCP, two Zenoh shards) training runs, a worker node is removed,
a replacement node joins, and RLlib (``restart_failed_env_runners``) restores the lost
runner: training goes on without an error, the new runner recreates its sessions (on the
shared server or the shards, where the server holds them), and ESA shifts its actions.
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np
import pytest

pytest.importorskip("ray.rllib")

import gymnasium as gym  # noqa: E402
import ray  # noqa: E402
from ray import cloudpickle  # noqa: E402
from ray.cluster_utils import Cluster  # noqa: E402
from ray.rllib.algorithms.ppo import PPOConfig  # noqa: E402
from ray.tune.registry import register_env  # noqa: E402

from esa_client import EsaClient, EsaConfig  # noqa: E402
from esa_client.rllib import EsaModuleToEnv, EsaService, with_esa  # noqa: E402

cloudpickle.register_pickle_by_value(sys.modules[__name__])

ENV = "esa-cluster-pendulum"
RUNNERS = 2
ENVS_PER_RUNNER = 2
RESTORE_S = 600
"""How long Ray and RLlib may take to bring the lost runner back on the new node."""


def make_env(_config=None):
    return gym.make("Pendulum-v1")


@pytest.fixture(scope="module")
def cluster(server_bin):
    """A head (no CPU for runners) and two one-CPU worker nodes, the driver connected."""
    saved = os.environ.get("ESA_SERVER_BIN")
    os.environ["ESA_SERVER_BIN"] = server_bin
    os.environ.setdefault("RAY_gcs_server_port_wait_time_s", "120")
    cluster = Cluster(
        initialize_head=True,
        head_node_args={"num_cpus": 0, "include_dashboard": False},
    )
    for _ in range(RUNNERS):
        cluster.add_node(num_cpus=1)
    cluster.wait_for_nodes()
    ray.init(address=cluster.address, log_to_driver=False, configure_logging=False)
    register_env(ENV, make_env)
    try:
        yield cluster
    finally:
        ray.shutdown()
        cluster.shutdown()
        if saved is None:
            os.environ.pop("ESA_SERVER_BIN", None)
        else:
            os.environ["ESA_SERVER_BIN"] = saved


def ppo_config() -> PPOConfig:
    return (
        PPOConfig()
        .environment(ENV)
        .env_runners(
            num_env_runners=RUNNERS,
            num_envs_per_env_runner=ENVS_PER_RUNNER,
            rollout_fragment_length=50,
            num_cpus_per_env_runner=1,
        )
        .training(train_batch_size_per_learner=200, minibatch_size=50, num_epochs=2)
        .fault_tolerance(
            restart_failed_env_runners=True,
            delay_between_env_runner_restarts_s=0.0,
            env_runner_health_probe_timeout_s=10.0,
        )
        .debugging(seed=0)
    )


def runner_state(runner):
    """Where a runner runs and what its ESA connector holds."""
    connector = next(c for c in runner._module_to_env.connectors if isinstance(c, EsaModuleToEnv))
    runtime = connector.runtime
    return {
        "node": ray.get_runtime_context().get_node_id(),
        "pid": os.getpid(),
        "sessions": None if runtime is None else runtime.batch.ids,
        "address": None if runtime is None else runtime.client.address,
    }


def runners(algo):
    return algo.env_runner_group.foreach_env_runner(runner_state, local_env_runner=False)


def train_through_node_loss(cluster, service):
    """Trains, loses a worker node, gets a new one, trains on; returns the runners' states."""
    # ESA's default for PPO, ungated so that it acts from the second iteration on.
    esa = EsaConfig.ppo(gate=None)
    algo = with_esa(ppo_config(), esa=esa, service=service, budget=100_000).build_algo()
    try:
        for _ in range(2):
            before = algo.train()
        states = runners(algo)
        assert len({s["node"] for s in states}) == RUNNERS, "runners on different nodes"
        assert all(s["sessions"] is not None for s in states)
        lost_node = next(n for n in cluster.worker_nodes if n.node_id == states[-1]["node"])
        cluster.remove_node(lost_node, allow_graceful=False)
        cluster.add_node(num_cpus=1)
        cluster.wait_for_nodes()
        # Training goes on with the runner left while Ray starts the lost one anew on the
        # new node (a minute or two on a loaded host); RLlib then restores it.
        deadline = time.monotonic() + RESTORE_S
        old = {s["pid"] for s in states}
        while True:
            algo.train()
            restored = runners(algo)  # the healthy ones
            if len(restored) == RUNNERS and {s["pid"] for s in restored} != old:
                break
            assert time.monotonic() < deadline, "the lost runner was not restored"
        # Two more updates: the restored runner gets the learner's weights (head, gate, fade).
        results = [algo.train() for _ in range(2)]
        after = runners(algo)
    finally:
        algo.stop()
    assert before["env_runners"]["esa/mean_abs_shift"] > 0
    assert np.isfinite(results[-1]["env_runners"]["esa/mean_abs_shift"])
    assert results[-1]["env_runners"]["esa/mean_abs_shift"] > 0, "ESA acts after the loss"
    assert len(after) == RUNNERS
    replaced = [s for s in after if s["pid"] not in {b["pid"] for b in states}]
    assert len(replaced) == 1 and replaced[0]["node"] != states[-1]["node"]
    for state in after:
        assert state["sessions"] is not None and len(state["sessions"]) == ENVS_PER_RUNNER
    return states, after


def test_sessions_in_each_runner_survive_a_lost_node(cluster):
    before, after = train_through_node_loss(cluster, EsaService())
    assert {s["address"] for s in after} == {"in-process"}


def test_one_shared_server_serves_runners_across_a_lost_node(cluster, server_bin, serve_tcp):
    with serve_tcp(server_bin) as address:
        _, after = train_through_node_loss(cluster, EsaService(address=address))
        with EsaClient.connect(address) as client:
            for state in after:
                assert state["address"] == address
                for session_id in state["sessions"]:
                    client.session_state(session_id)  # the server holds every new session


def test_zenoh_shards_serve_runners_across_a_lost_node(cluster, server_bin, tmp_path):
    with EsaClient.spawn(server_bin, transport="zenoh", shards=2) as shards:
        token = tmp_path / "token"
        token.write_text(shards.servers[0].token or "")
        service = EsaService(zenoh=shards.address.split(","), shards=2, token_file=str(token))
        _, after = train_through_node_loss(cluster, service)
        for state in after:
            for session_id in state["sessions"]:
                shards.session_state(session_id)  # on the shard its id hashes to
