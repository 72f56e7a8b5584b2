"""Summarizes py-spy ``--format raw`` profiles of ``run_one.py``: ESA's buckets, top frames.

Only samples under ``learn()`` count. Each sample goes to the first bucket whose frame is
on its stack (``BUCKETS``, in order); in ESAPPO's forward pass, the policy's own calls
(``POLICY_CALLS``) count as PPO's, the rest (and the forward's own lines: numpy and
tensor conversions) as ESA's glue.

Usage::

    python bench/profiles/summarize.py bench/out/before/*.txt[.gz]
"""

from __future__ import annotations

import gzip
import re
import sys
from collections import Counter
from pathlib import Path

BUCKETS: list[tuple[str, str]] = [
    (
        "SessionBatch calls (engine or transport)",
        r"^(probe_applied|flush|report|restore) \(.*session\.py:",
    ),
    # q_fn: the torch head of the profiles up to 48d7c6a; then the head in Rust (7ee1b71 on).
    ("head forward at the probes (q_fn)", r"^(q_fn \(.*ppo\.py:|(_esa_critic|_esa_weights) \()"),
    ("runtime stats", r"^(add_step|_fold|add_improvement|means|record) \(.*runtime\.py:"),
    ("runtime step, rest", r"^step \(.*runtime\.py:"),
    ("runtime open (sessions, spawn)", r"^_esa_runtime \("),
    ("head fit", r"^fit \(.*advantage_head\.py:"),
    ("gate (critic_quality)", r"^critic_quality \("),
    ("head data (policy over the rollout)", r"^_update_esa_head \("),
    (
        "ESA glue in forward (head features, conversions)",
        r"^(_head_features|_step_features|_esa_q_at|_to_esa_units|_esa_scaling|_gradient_shift) \(",
    ),
    ("ESA logging", r"^(dump_logs) \(.*mixin\.py:"),
]
FORWARD = re.compile(r"^forward \(.*sb3/ppo\.py:(\d+)\)$")
POLICY_CALLS = (
    "extract_features (",
    "_wrapped_call_impl (",
    "forward_actor (",
    "forward_critic (",
    "_get_action_dist_from_latent (",
    "get_actions (",
    "log_prob (",
)
"""What ``_esa_forward`` calls that PPO's own forward calls too; the rest is ESA's."""


def short(frame: str) -> str:
    """A frame without its qualified name's prefix: ``forward (file:line)``."""
    func, sep, where = frame.partition(" (")
    return func.rsplit(".", 1)[-1] + sep + where


def read(path: Path) -> list[tuple[list[str], int]]:
    """The (frames, count) pairs of a raw profile, outermost frame first."""
    opener = gzip.open if path.suffix == ".gz" else open
    stacks = []
    with opener(path, "rt") as f:
        for line in f:
            line = line.rstrip("\n")
            if not line:
                continue
            stack, _, count = line.rpartition(" ")
            stacks.append(([short(f) for f in stack.split(";")], int(count)))
    return stacks


def bucket(frames: list[str]) -> str:
    """The bucket of one sample under learn()."""
    for name, pattern in BUCKETS:
        regex = re.compile(pattern)
        if any(regex.match(frame) for frame in frames):
            return name
    for i, frame in enumerate(frames):
        if FORWARD.match(frame):
            child = frames[i + 1] if i + 1 < len(frames) else ""
            if not child.startswith(POLICY_CALLS):
                return "ESA glue in forward (head features, conversions)"
    if any(f.startswith("collect_rollouts (") for f in frames):
        return "PPO: collect_rollouts (policy forward, env step, buffer)"
    if any(f.startswith("train (") for f in frames):
        return "PPO: train (gradient update)"
    return "other"


def summarize(path: Path) -> tuple[Counter, Counter, int]:
    """Samples per bucket and per leaf frame under learn(), and their total."""
    buckets: Counter = Counter()
    leaves: Counter = Counter()
    total = 0
    for frames, count in read(path):
        learn = [i for i, f in enumerate(frames) if f.startswith("learn (") and "ppo" in f]
        if not learn:
            continue
        inner = frames[learn[0] :]
        buckets[bucket(inner)] += count
        leaves[inner[-1]] += count
        total += count
    return buckets, leaves, total


def main() -> None:
    """Prints each profile's buckets and top leaf frames."""
    for arg in sys.argv[1:]:
        buckets, leaves, total = summarize(Path(arg))
        print(f"## {Path(arg).name}: {total} samples under learn()\n")
        print("| bucket | samples | share of learn() |\n|---|---:|---:|")
        for name, n in buckets.most_common():
            print(f"| {name} | {n} | {n / total:.3f} |")
        print("\nTop leaf frames:\n")
        for frame, n in leaves.most_common(12):
            print(f"- {n / total:.3f} {frame}")
        print()


if __name__ == "__main__":
    main()
