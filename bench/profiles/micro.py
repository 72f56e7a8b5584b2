"""CPU microseconds of the head's per-step forward and of one fit, before and after.

Before: ``head.w(tile_obs(features, 2))`` and ``Adam(foreach=None)`` with the module
call in the fit's forward; after: ``head.weights(features.repeat(2, 1))`` and
``Adam(foreach=True)``. Alternating blocks in one process, ``time.process_time``.

Usage::

    python bench/profiles/micro.py
"""

from __future__ import annotations

import time

import numpy as np
import torch as th
from esa_client.common.advantage_head import AdvantageHead, Rollout, fit
from esa_client.sb3.mixin import tile_obs


def per_call(fn, calls: int) -> float:  # type: ignore[no-untyped-def]
    """CPU microseconds per call of ``fn``."""
    start = time.process_time()
    for _ in range(calls):
        fn()
    return (time.process_time() - start) / calls * 1e6


def main() -> None:
    """Prints the medians over alternating blocks."""
    th.set_num_threads(1)
    for n in (1, 8):
        head = AdvantageHead(4, 1)
        features = th.randn(n, 4)
        with th.no_grad():
            old = lambda h=head, f=features: h.w(tile_obs(f, 2))  # noqa: E731
            new = lambda h=head, f=features: h.weights(f.repeat(2, 1))  # noqa: E731
            times: dict[str, list[float]] = {"before": [], "after": []}
            for _ in range(7):
                times["before"].append(per_call(old, 3000))
                times["after"].append(per_call(new, 3000))
        med = {k: float(np.median(v)) for k, v in times.items()}
        print(
            f"head forward, {n} env(s), paired probes: before {med['before']:.1f} us, "
            f"after {med['after']:.1f} us per step"
        )
    rollouts = [Rollout(th.randn(2048, 4), th.randn(2048, 1), th.randn(2048)) for _ in range(4)]
    fits: dict[str, list[float]] = {"before": [], "after": []}
    for _ in range(3):
        for name, foreach in (("before", None), ("after", True)):
            head = AdvantageHead(4, 1)
            if name == "before":
                head.weights = head.w  # type: ignore[method-assign]
            opt = th.optim.Adam(head.parameters(), lr=1e-3, foreach=foreach)
            rng = np.random.default_rng(0)
            start = time.process_time()
            fit(head, opt, rollouts, epochs=5, batch_size=256, rng=rng)
            fits[name].append((time.process_time() - start) * 1e3)
    med = {k: float(np.median(v)) for k, v in fits.items()}
    print(
        f"head fit (4 rollouts x 2048, 5 epochs, batch 256): before {med['before']:.0f} ms, "
        f"after {med['after']:.0f} ms"
    )


if __name__ == "__main__":
    main()
