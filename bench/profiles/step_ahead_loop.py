"""The client's cost of one ESAPPO-shaped step through the native sidecar, in a tight loop.

One spawned esa-server on a Unix socket, the Rust client of ``esa_client._native`` on the
batch's StepStream; ``--steps`` steps of a linear critic by ``SessionBatch.step``, either
waiting for its probes (``step``: the probe and the deferred report, one round trip that the
call waits for) or sent ahead (``ahead``: one ``step_linear_batch`` message sent without
waiting, its answer read at the next call). Prints the wall-clock and the client's CPU time
per step; with nothing between the steps the answer of a step sent ahead has not arrived yet,
so the wall-clock here is an upper bound of what a trainer waits.

Usage::

    python bench/profiles/step_ahead_loop.py [--n 1] [--steps 20000] [--modes ahead,step]
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import tyro
from esa_client import EsaClient, LinearCritic, SessionConfig


@dataclass
class Args:
    """The client's cost of one ESAPPO-shaped step through the native sidecar, in a loop."""

    n: int = 1
    """Sessions (envs)."""
    steps: int = 20_000
    """Steps per mode."""
    modes: str = "ahead,step,ahead,step"
    """Modes to run in order, comma-separated: ahead and/or step."""


def main(args: Args) -> None:
    """Runs the modes one after another on one server and prints their cost per step."""
    config = SessionConfig(
        action_dim=1, dt=0.04, amplitude=[0.2], frequency=[30.0], learning_rate=[0.1]
    )
    rng = np.random.default_rng(0)
    actions = rng.normal(size=(args.n, 1))
    critic = LinearCritic(np.ones((args.n, 1)), np.zeros(args.n))
    starts = np.zeros(args.n, dtype=bool)
    with EsaClient.spawn() as client:
        for mode in args.modes.split(","):
            batch = client.create_batch(config, args.n, use_stream=True)
            wall, cpu = time.perf_counter(), time.process_time()
            for _ in range(args.steps):
                # "step" waits for each answer, as a trainer that needs the probes does.
                batch.step(actions, critic, starts, want_probes=mode == "step")
            batch.flush()
            wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
            print(
                f"{mode:>5}: wall {wall / args.steps * 1e6:6.1f} us/step, "
                f"client CPU {cpu / args.steps * 1e6:6.1f} us/step"
            )
            batch.close()


if __name__ == "__main__":
    main(tyro.cli(Args))
