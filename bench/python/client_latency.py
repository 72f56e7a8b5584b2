"""SessionBatch pair latency from Python, per transport, vs in-process and vs a grpcio baseline.

One pair is what a trainer does per VecEnv step: ``batch.probe(actions, starts)``,
the critic at the probes (here ``-|probe|^2``), ``batch.report(q)``. Measured for
N = 1, 8, 64 envs of D = 6 against:

- esa-server over loopback TCP and a Unix socket (``EsaClient.spawn``), each with
  ``ProbeBatch``/``ReportBatch`` calls and with the ``StepStream``;
- esa-server with ``--zenoh`` on loopback (``ZenohEsaClient.spawn``): the same two
  ways, as queries on ``esa/v1/ProbeBatch``/``ReportBatch`` or one query per
  StepStream message on ``esa/v1/StepStream``;
- ``esa_client.reference`` in-process (no server, no network);
- ``baseline_server.py``, a plain Python grpcio server, through the same client.

Usage::

    python bench/python/client_latency.py [--window 2.0] [--out bench/results/python.json]
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager, nullcontext
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from esa_client import EsaClient, SessionConfig, ZenohEsaClient
from esa_client.reference import ReferenceClient

from cli import parse_dataclass
from servers import baseline_server, esa_server_tcp, server_binary

# Steps per episode, as in the MuJoCo tasks (the episode start rides on a probe).
EPISODE_STEPS = 1000


@dataclass
class Args:
    """Benchmark settings (all overridable on the command line)."""

    envs: str = "1,8,64"
    dim: int = 6
    warmup: float = 0.3
    window: float = 2.0
    max_pairs: int = 20_000
    out: str = "bench/results/python.json"


def session_config(dim: int) -> SessionConfig:
    """The same per-session config as the Rust load generator sends."""
    return SessionConfig(
        action_dim=dim,
        dt=0.01,
        amplitude=0.2,
        frequency=[40.0 + 5.0 * i for i in range(dim)],
        learning_rate=0.05,
        action_low=-1.0,
        action_high=1.0,
    )


def measure(batch, args: Args) -> dict:
    """Runs pairs on ``batch`` for the warm-up, then times each pair; returns the summary."""
    rng = np.random.default_rng(0)
    actions = rng.uniform(-0.5, 0.5, size=(batch.n, batch.action_dim))

    def pair(step: int) -> None:
        if step % EPISODE_STEPS == 0:
            batch.reset()
        probes = batch.probe(actions)
        batch.report(-np.sum(probes**2, axis=1))

    step = 0
    end = time.perf_counter() + args.warmup
    while time.perf_counter() < end:
        pair(step)
        step += 1
    times = []
    end = time.perf_counter() + args.window
    while len(times) < args.max_pairs and time.perf_counter() < end:
        start = time.perf_counter_ns()
        pair(step)
        times.append(time.perf_counter_ns() - start)
        step += 1
    us = np.asarray(times) / 1e3
    return {
        "pairs": len(times),
        "p50_us": float(np.percentile(us, 50)),
        "p90_us": float(np.percentile(us, 90)),
        "p99_us": float(np.percentile(us, 99)),
        "mean_us": float(us.mean()),
        "session_steps_per_s": float(batch.n / (us.mean() / 1e6)),
    }


@contextmanager
def client_at(address: AbstractContextManager[str]) -> Iterator[EsaClient]:
    """An ``EsaClient`` on the address a server context yields."""
    with address as target, EsaClient(target, timeout=30.0) as client:
        yield client


Target = tuple[str, str, str, Callable[[], AbstractContextManager]]
"""(server, socket, api, a factory of a context yielding a client)."""


def targets() -> list[Target]:
    """Every (server, socket, api) combination this benchmark measures."""
    out: list[Target] = []
    for api in ("batch", "stream"):
        out.append(("esa-server", "tcp", api, lambda: client_at(esa_server_tcp())))
        out.append(
            ("esa-server", "uds", api, lambda: EsaClient.spawn(server_binary(), timeout=30.0))
        )
        out.append(
            (
                "esa-server",
                "zenoh",
                api,
                lambda: ZenohEsaClient.spawn(server_binary(), timeout=30.0),
            )
        )
        out.append(("python-grpcio", "tcp", api, lambda: client_at(baseline_server())))
    out.append(("reference", "in-process", "-", lambda: nullcontext(ReferenceClient())))
    return out


def main() -> None:
    """Measures every target for every N and writes the JSON results."""
    args = parse_dataclass(Args, __doc__.splitlines()[0])
    envs = [int(n) for n in args.envs.split(",")]
    rows = []
    for server, socket, api, connect in targets():
        with connect() as client:
            for n in envs:
                batch = client.create_batch(session_config(args.dim), n, use_stream=api == "stream")
                result = measure(batch, args)
                batch.close()
                row = {"server": server, "socket": socket, "api": api, "envs": n, **result}
                rows.append(row)
                print(
                    f"{server:<14} {socket:<10} {api:<6} N={n:<3} p50 {row['p50_us']:8.1f} us"
                    f"  p99 {row['p99_us']:8.1f} us  {row['session_steps_per_s']:10.0f} steps/s",
                    flush=True,
                )
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"args": dataclasses.asdict(args), "rows": rows}, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
