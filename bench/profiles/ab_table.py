"""The before/after table from ``cpu_ratio.py --before``'s log (complete repeats only).

Per repeat, each ESAPPO run's CPU seconds (trainer + sidecar server) over the same
repeat's PPO run; the median over repeats.

Usage::

    python bench/profiles/ab_table.py bench/out/cpu_ratio_ab.log
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import numpy as np

LINE = re.compile(r"^(\d+) env\(s\) (.+?)\s+cpu\s+([\d.]+) s \+ server\s+([\d.]+) s")


def main() -> None:
    """Prints the markdown table."""
    runs: dict[int, list[list[tuple[str, float]]]] = {}
    for line in Path(sys.argv[1]).read_text().splitlines():
        m = LINE.match(line)
        if not m:
            continue
        n_envs, name, cpu = int(m[1]), m[2].strip(), float(m[3]) + float(m[4])
        repeats = runs.setdefault(n_envs, [])
        if name == "PPO":
            repeats.append([])
        repeats[-1].append((name, cpu))
    print("| envs | agent | ratio before (median) | ratio after (median) | repeats |")
    print("|---:|---|---:|---:|---:|")
    for n_envs, repeats in runs.items():
        width = max(len(r) for r in repeats)
        complete = [dict(r) for r in repeats if len(r) == width]
        names = [n for n in complete[0] if n != "PPO" and not n.endswith(" before")]
        for name in names:
            after = [r[name] / r["PPO"] for r in complete]
            before = [r[f"{name} before"] / r["PPO"] for r in complete if f"{name} before" in r]
            print(
                f"| {n_envs} | {name} | {np.median(before):.3f} {np.round(before, 3).tolist()} "
                f"| {np.median(after):.3f} {np.round(after, 3).tolist()} | {len(complete)} |"
            )


if __name__ == "__main__":
    main()
