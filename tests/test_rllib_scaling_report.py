"""bench/report.py's RLlib scaling section: the shards formula, the ratios and the verdicts.

On made-up rows of ``bench/python/rllib_scaling.py``'s JSON and esa-bench's throughput rows,
so the page's arithmetic is checked without running RLlib.
"""

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import report
from report import Run, rllib_rows, rllib_section, shards_needed


def test_shards_formula():
    # ceil(N * r * (1 + h) / C), at least one server.
    assert shards_needed(1, 400.0, 16_000.0) == 1
    assert shards_needed(8, 400.0, 16_000.0) == 1
    assert shards_needed(64, 400.0, 16_000.0) == 3  # 38,400 / 16,000 = 2.4
    assert shards_needed(1000, 400.0, 16_000.0) == 38  # 600,000 / 16,000 = 37.5
    assert shards_needed(1000, 400.0, 16_000.0, headroom=0.0) == 25
    assert shards_needed(40, 400.0, 16_000.0, headroom=0.0) == 1  # exactly full
    with pytest.raises(ValueError):
        shards_needed(0, 400.0, 16_000.0)
    with pytest.raises(ValueError):
        shards_needed(1, 400.0, 0.0)


def row(setup, esa, runners, rate, repeat=0, active=None):
    return {
        "algo": "PPO",
        "runners": runners,
        "setup": setup,
        "esa": esa,
        "repeat": repeat,
        "env_steps_per_s": rate,
        "esa_active": active,
        "session_steps_per_s": None if active is None else rate * active,
        "server_requests_per_s": rate * active if setup == "shared" else None,
        "loadavg_1m_before": 1.0,
    }


def scaling(cores=2):
    rows = []
    for repeat, slow in enumerate((1.0, 1.09)):
        for n in (1, 2):
            rows += [
                row("plain", None, n, 1000.0 * n, repeat),
                row("in-runner", "ungated", n, 1000.0 * n / (1.05 * slow), repeat, 1.0),
                row("shared", "ungated", n, 1000.0 * n / (1.25 * slow), repeat, 1.0),
                row("shared", "default", n, 1000.0 * n, repeat, 0.0),
            ]
    host = {"cores": cores, "ram_gib": 8.0, "loadavg": [1.0, 1.0, 1.0]}
    args = {
        "warmup": 1,
        "iterations": 1,
        "ppo_batch": 1000,
        "ppo_epochs": 1,
        "sac_steps": 200,
        "sac_learning_starts": 200,
        "repeats": 2,
    }
    return {
        "args": args,
        "env": "Pendulum-v1",
        "shards": 2,
        "host_start": host,
        "host_end": host,
        "wall_s": 60.0,
        "rows": rows,
    }


def test_rows_are_medians_with_ratios_against_plain_of_the_same_repeat():
    rows = rllib_rows(scaling())
    assert [(r["runners"], r["setup"], r["esa"]) for r in rows[:4]] == [
        (1, "plain", "-"),
        (1, "in-runner", "ungated"),
        (1, "shared", "default"),
        (1, "shared", "ungated"),
    ]
    in_runner = rows[1]
    assert in_runner["ratio"] == pytest.approx((1.05 + 1.05 * 1.09) / 2)
    assert report.rllib_verdict(in_runner) == "PASS"  # 1.097 against 1.10x
    shared = rows[3]
    assert shared["ratio"] == pytest.approx((1.25 + 1.25 * 1.09) / 2)
    assert report.rllib_verdict(shared) == "MISS"
    assert report.rllib_verdict(rows[0]) == "-"


def test_section_works_the_formula_from_the_one_runner_shared_row():
    server = {
        "throughput": [
            {
                "socket": "tcp",
                "api": "stream",
                "batch": 1,
                "concurrency": 4,
                "session_steps_per_s": 16_000.0,
            },
            {
                "socket": "zenoh",
                "api": "stream",
                "batch": 1,
                "concurrency": 4,
                "session_steps_per_s": 5_000.0,
            },
        ]
    }
    run = Run(None, None, server, None, None, None, None, scaling())
    text = "\n".join(rllib_section(run))
    assert "**CPU-bound rows.**" in text
    # r = the ungated 1-runner shared row: the median of its two repeats.
    rate = (1000 / 1.25 + 1000 / (1.25 * 1.09)) / 2
    assert f"| PPO | 1,000 | {rate:,.0f} | {1000 * rate:,.0f} | " in text
    assert (
        f"| {shards_needed(1000, rate, 16_000.0)} | {shards_needed(1000, rate, 5_000.0)} |"
        in text
    )


def test_a_large_host_is_not_called_cpu_bound():
    run = Run(None, None, {"throughput": []}, None, None, None, None, scaling(cores=16))
    text = "\n".join(rllib_section(run))
    assert "CPU-bound" not in text
    assert "no esa-bench throughput rows" in text
