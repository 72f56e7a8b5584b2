"""Micro-benchmark of esa_client._native: one probe + report pair of N sessions, in-process.

Default: N = 8 sessions of D = 6 (the target: p50 <= 10 us per pair), once with section 1's
law (no action scales, no references) and once with every section 1b field on (scales with each
probe, references with each report). ``--gil`` measures what releasing the GIL costs per call
against the call's own time for growing batches, which is how ``DETACH_VALUES`` was chosen.

    .venv/bin/python client-py/native/bench_engine.py [--sessions 8] [--dim 6] [--pairs 20000]
    .venv/bin/python client-py/native/bench_engine.py --gil
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from esa_client import SessionConfig
from esa_client._native import DETACH_VALUES, Engine


def make_engine(n: int, dim: int, section_1b: bool, detach_values: int = DETACH_VALUES):
    """An engine with n sessions of dim action dimensions, and the handle of all of them."""
    config = SessionConfig(
        action_dim=dim,
        dt=0.01,
        amplitude=0.1,
        frequency=tuple(40.0 + 2.0 * (i % 64) for i in range(dim)),
        learning_rate=0.25,
        action_low=-1.0,
        action_high=1.0,
        shift_limit=0.5,
        normalize_response=section_1b,
        shift_leak=0.005 if section_1b else None,
        trust_region=1.0 if section_1b else None,
    )
    engine = Engine(detach_values=detach_values)
    encoded = config.to_proto().SerializeToString()
    ids = [engine.create_session(f"bench-{i}", encoded) for i in range(n)]
    return engine, engine.resolve(ids)


def time_pairs(n: int, dim: int, pairs: int, section_1b: bool, detach_values: int = DETACH_VALUES):
    """Nanoseconds of each probe + report pair (episodes of 1000 steps, like MuJoCo tasks)."""
    engine, handle = make_engine(n, dim, section_1b, detach_values)
    rng = np.random.default_rng(0)
    actions = rng.uniform(-0.5, 0.5, size=(n, dim))
    scales = np.full((n, dim), 0.3) if section_1b else None
    steps = np.zeros(n, dtype=np.uint64)
    starts = np.ones(n, dtype=bool)
    no_starts = np.zeros(n, dtype=bool)
    q = np.zeros(n)
    references = np.zeros(n) if section_1b else None
    times = np.empty(pairs, dtype=np.int64)
    clock = time.perf_counter_ns
    for i in range(pairs):
        t = i % 1000
        steps.fill(t)
        begin = clock()
        probes, applied = engine.probe(
            handle, steps, actions, starts if t == 0 else no_starts, scales
        )
        np.sum(probes, axis=1, out=q)  # a stand-in critic, inside the timed pair
        if references is not None:
            np.sum(applied, axis=1, out=references)
        engine.report(handle, steps, q, references)
        times[i] = clock() - begin
    return times


def pair_table(args) -> None:
    """p50/p90/p99 of the pair for section 1 and section 1b."""
    print(f"esa_client._native: N = {args.sessions} sessions, D = {args.dim}, {args.pairs} pairs")
    print(f"{'law':<12}{'p50 us':>10}{'p90 us':>10}{'p99 us':>10}")
    for name, section_1b in (("section 1", False), ("section 1b", True)):
        times = time_pairs(args.sessions, args.dim, args.pairs // 10, section_1b)  # warm-up
        times = time_pairs(args.sessions, args.dim, args.pairs, section_1b)
        p50, p90, p99 = np.percentile(times, [50, 90, 99]) / 1e3
        print(f"{name:<12}{p50:>10.2f}{p90:>10.2f}{p99:>10.2f}")


def gil_table(args) -> None:
    """Per batch size: the pair's p50 holding the GIL, releasing it, and the difference."""
    print("GIL release cost per pair (section 1b law, D = 64): p50 in us")
    print(f"{'N*D':>8}{'hold':>10}{'release':>10}{'cost':>10}{'cost %':>8}")
    dim = 64
    for n in (1, 2, 4, 8, 16, 32, 64, 128, 256):
        pairs = max(200, args.pairs // n)
        hold = np.median(time_pairs(n, dim, pairs, True, detach_values=1 << 62)) / 1e3
        release = np.median(time_pairs(n, dim, pairs, True, detach_values=0)) / 1e3
        cost = release - hold
        print(f"{n * dim:>8}{hold:>10.2f}{release:>10.2f}{cost:>10.2f}{100 * cost / hold:>8.1f}")


def main() -> None:
    """Runs the pair table, or the GIL table with --gil."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sessions", type=int, default=8)
    parser.add_argument("--dim", type=int, default=6)
    parser.add_argument("--pairs", type=int, default=20_000)
    parser.add_argument("--gil", action="store_true", help="measure the cost of releasing the GIL")
    args = parser.parse_args()
    if args.gil:
        gil_table(args)
    else:
        pair_table(args)


if __name__ == "__main__":
    main()
