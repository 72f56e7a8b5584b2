"""Where the ESAPPO / PPO CPU-time gap goes: profile shares times measured CPU seconds.

Each ESA bucket's share of ``learn()``'s samples (``summarize.py``) times the ESA run's
median trainer CPU seconds (``cpu_ratio.py``'s log), over PPO's median CPU seconds: the
bucket's part of the ratio, in units of PPO's time. The sidecar's esa-server CPU is its
own row. "rest" is the measured ratio minus 1 minus the ESA rows: PPO's own work
sampled as larger (or smaller) in the ESA run, i.e. noise and cache effects.

Usage::

    python bench/profiles/gap_table.py bench/out/cpu_ratio_before.log bench/out/before
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import numpy as np
from summarize import BUCKETS, summarize

LINE = re.compile(r"^(\d+) env\(s\) (.+?)\s+cpu\s+([\d.]+) s \+ server\s+([\d.]+) s")
COLUMNS = [(1, "inprocess"), (1, "sidecar"), (8, "inprocess"), (8, "sidecar")]
PPO_BUCKETS = ("PPO: ", "other")


def main() -> None:
    """Prints the markdown table."""
    log, profiles = Path(sys.argv[1]), Path(sys.argv[2])
    cpu: dict[tuple[int, str], list[tuple[float, float]]] = {}
    for line in log.read_text().splitlines():
        m = LINE.match(line)
        if m:
            cpu.setdefault((int(m[1]), m[2].strip()), []).append((float(m[3]), float(m[4])))
    names = [name for name, _ in BUCKETS] + ["ESA glue in forward (head features, conversions)"]
    names = list(dict.fromkeys(names))
    rows: dict[str, list[str]] = {name: [] for name in names}
    extra: dict[str, list[str]] = {
        k: []
        for k in (
            "esa-server process",
            "sum of ESA rows",
            "rest (PPO's own work, noise)",
            "measured ratio (median)",
            "runs",
        )
    }
    for n_envs, engine in COLUMNS:
        ppo = np.median([t for t, _ in cpu[(n_envs, "PPO")]])
        runs = cpu.get((n_envs, f"ESAPPO [{engine}]"), [])
        trainer = np.median([t for t, _ in runs])
        server = np.median([s for _, s in runs])
        ratio = np.median(
            [(t + s) / p for (t, s), (p, _) in zip(runs, cpu[(n_envs, "PPO")], strict=True)]
        )
        name = f"ESAPPO-{engine}-{n_envs}env.txt"
        path = profiles / name if (profiles / name).exists() else profiles / f"{name}.gz"
        buckets, _, total = summarize(path)
        esa = 0.0
        for name in names:
            part = buckets.get(name, 0) / total * trainer / ppo
            esa += part
            rows[name].append(f"{part:.3f}")
        esa += server / ppo
        extra["esa-server process"].append(f"{server / ppo:.3f}")
        extra["sum of ESA rows"].append(f"{esa:.3f}")
        extra["rest (PPO's own work, noise)"].append(f"{ratio - 1 - esa:+.3f}")
        extra["measured ratio (median)"].append(f"{ratio:.3f}")
        extra["runs"].append(str(len(runs)))
    heads = [f"{n} env{'s' if n > 1 else ''}, {e}" for n, e in COLUMNS]
    print("| part of ESAPPO/PPO CPU time (x PPO) | " + " | ".join(heads) + " |")
    print("|---|" + "---:|" * len(COLUMNS))
    for name, values in {**rows, **extra}.items():
        print(f"| {name} | " + " | ".join(values) + " |")


if __name__ == "__main__":
    main()
