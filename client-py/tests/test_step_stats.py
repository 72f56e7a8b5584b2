"""``StepStats``: the sums behind a learner's per-step ``esa/`` statistics.

Each statistic is a mean over the envs of one step, then over the steps since the last
record, whatever the env count of each step; counts are totals. Bad shapes are refused and
change nothing.
"""

import numpy as np
import pytest

from esa_client._native import StepStats


def _stats() -> StepStats:
    return StepStats([-1.0, -1.0], [1.0, 1.0])


def test_statistics_are_per_step_means_whatever_the_env_count():
    rng = np.random.default_rng(0)
    steps = [
        (rng.normal(size=(n, 2)), rng.normal(size=(n, 2)), rng.uniform(0.5, 1.0, size=(n, 2)))
        for n in [3] * 300 + [5] * 10
    ]
    stats = _stats()
    for sampled, applied, std in steps:
        # float32 scales are read as numpy widens them.
        stats.add_step(sampled, applied, std.astype(np.float32))
    stats.add_improvement(0.5)
    stats.add_improvement(1.5)
    want = {
        "mean_abs_shift": np.mean([np.abs(a - s).mean() for s, a, _ in steps]),
        "clipped_fraction": np.mean([np.any(np.abs(a) > 1, axis=1).mean() for _, a, _ in steps]),
        "shift_over_std": np.mean(
            [np.abs((a - s) / d.astype(np.float32)).mean() for s, a, d in steps]
        ),
        "kl_per_dim": np.mean(
            [(0.5 * ((a - s) / d.astype(np.float32)) ** 2).mean() for s, a, d in steps]
        ),
        "improvement": 1.0,
    }
    assert stats.means() == pytest.approx(want, rel=1e-12)


def test_steps_without_a_std_count_only_where_they_apply_and_counts_are_totals():
    stats = _stats()
    stats.add_step(np.zeros((2, 2)), np.full((2, 2), 2.0))
    stats.add_step(np.zeros((2, 2)), np.zeros((2, 2)), np.ones((2, 2)))
    stats.add_count("sessions_restored", 2)
    stats.add_count("sessions_restored", 3)
    assert stats.means() == {
        "mean_abs_shift": 1.0,
        "clipped_fraction": 0.5,
        "shift_over_std": 0.0,
        "kl_per_dim": 0.0,
        "sessions_restored": 5.0,
    }
    stats.reset()
    assert stats.means() == {}


def test_bad_shapes_are_refused_and_change_nothing():
    stats = _stats()
    with pytest.raises(ValueError, match=r"expected applied of shape \(2, 2\), got \[3, 2\]"):
        stats.add_step(np.zeros((2, 2)), np.zeros((3, 2)))
    with pytest.raises(ValueError, match=r"expected sampled of shape \(N, 2\), got \[2, 3\]"):
        stats.add_step(np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(TypeError, match="applied: expected a numpy array"):
        stats.add_step(np.zeros((2, 2)), [[0.0, 0.0], [0.0, 0.0]])
    with pytest.raises(ValueError, match=r"expected scales of shape \(2, 2\), got \[1, 2\]"):
        stats.add_step(np.zeros((2, 2)), np.zeros((2, 2)), np.ones((1, 2)))
    assert stats.means() == {}
    with pytest.raises(ValueError, match="expected clip_low and clip_high of one length"):
        StepStats([0.0], [1.0, 2.0])
