"""Algorithm 1's step through the native client: unary calls against its StepStream.

One spawned esa-server on a Unix socket, the Rust client of ``esa_client._native``; per
N, ``--rounds`` alternating windows of the section 1b step (``client_latency.measure``:
``probe_applied``, the critic at the probes and the applied actions, ``report``), as two
unary calls (``use_stream=False``) and as the pipelined pair on the batch's StepStream
(``use_stream=True``, the report deferred). Prints the mean time per step of each window.

Usage::

    python bench/profiles/native_stream_ab.py [--rounds 6] [--window 1.0] [--out FILE]
"""

from __future__ import annotations

import dataclasses
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro
from esa_client import EsaClient

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "python"))
from client_latency import Args as LatencyArgs  # noqa: E402
from client_latency import measure, section_1b_config  # noqa: E402
from servers import server_binary  # noqa: E402

MODES = {"unary": ("pair", False), "stream": ("pipelined", True)}


@dataclass
class Args:
    """Algorithm 1's step through the native client: unary calls against its StepStream."""

    envs: str = "1,8"
    """Batch sizes N (envs), comma-separated."""
    rounds: int = 6
    """Rounds of one window per mode."""
    window: float = 1.0
    """Seconds per window."""
    out: str = ""
    """JSON of the step times (empty: print only)."""


def main(options: Args) -> None:
    """Runs the alternating windows and prints (and optionally writes) the step times."""
    args = LatencyArgs(window=options.window, warmup=0.3)
    rows = []
    with EsaClient.spawn(server_binary(), timeout=30.0) as client:
        for n in (int(n) for n in options.envs.split(",")):
            means: dict[str, list[float]] = {mode: [] for mode in MODES}
            for _ in range(options.rounds):
                for mode, (step, use_stream) in MODES.items():
                    batch = client.create_batch(section_1b_config(6), n, use_stream=use_stream)
                    means[mode].append(measure(batch, args, "1b", step)["mean_us"])
                    batch.close()
            for mode, values in means.items():
                median = float(np.median(values))
                rows.append({"envs": n, "mode": mode, "median_us": median, "windows_us": values})
                print(f"N={n:<3} {mode:<7} median {median:6.1f} us  windows {np.round(values, 1)}")
    if options.out:
        Path(options.out).write_text(
            json.dumps({"args": dataclasses.asdict(options), "rows": rows}, indent=1)
        )


if __name__ == "__main__":
    main(tyro.cli(Args))
