"""Smoke tests of the quadrotor figure script and the throughput benchmark."""

import subprocess
import sys
from pathlib import Path

EXPERIMENTS = Path(__file__).resolve().parents[1]


def _run(script: str, *args: str) -> str:
    result = subprocess.run(
        [sys.executable, str(EXPERIMENTS / script), *args],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    return result.stdout


def test_pd_figure_script_writes_both_pngs(tmp_path):
    out = _run("scripts/quadrotor_pd_figures.py", "--out-dir", str(tmp_path))
    for path in ("circle", "eight"):
        assert (tmp_path / f"pd_{path}.png").read_bytes()[:4] == b"\x89PNG"
        assert f"{path}" in out
    assert "mean error" in out


def test_throughput_bench_runs_and_reports_steps_per_second():
    out = _run("bench/quadrotor_throughput.py", "--steps", "300", "--repeats", "1")
    assert out.count("steps/s wall") == 2
