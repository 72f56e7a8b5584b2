"""bench/report.py's provenance: per part, when, at which commit and under which load it ran.

``bench/run.sh --only PARTS`` re-runs some parts and keeps the others' results; run.json then
holds a record per part that ran, and the whole run's record (an older run.json's only one)
for the parts without their own. On made-up records, so nothing is run.
"""

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from report import Run, machine_section, provenance_lines


def record(started, finished, commit, mean, peak, cores=2, quick=None, commands=("x",)):
    out = {
        "cpu_model": "AMD EPYC",
        "cores": cores,
        "ram_gib": 23.5,
        "kernel": "Linux-6",
        "started": started,
        "finished": finished,
        "commit": commit,
        "loadavg_start": "1.00 1.00 1.00 1/100 1",
        "loadavg_end": "1.00 1.00 1.00 1/100 2",
        "load_interval_s": 5,
        "loadavg": {"samples": 10, "min": 1.0, "mean": mean, "max": peak},
        "cpu_time_percent": {
            "user": 40.0,
            "system": 5.0,
            "idle": 50.0,
            "iowait": 1.0,
            "steal": 2.5,
        },
        "cpuidle": {"driver": None},
        "commands": list(commands),
    }
    if quick is not None:
        out["quick"] = quick
    return out


WHOLE = record("2026-11-29T03:25:33Z", "2026-11-29T04:19:06Z", "2be47cc", 1.17, 3.04)


def results(run_json, **parts):
    """A Run with results for ``parts`` (e.g. core=True) and this run.json."""
    fields = (
        "core",
        "server",
        "python",
        "section_1b",
        "training",
        "sizes",
        "rllib_scaling",
    )
    return Run(run_json, *({"rows": []} if parts.get(f) else None for f in fields))


def rows(lines):
    """The header table's rows, by part."""
    lines = "\n".join(lines).splitlines()
    return {
        line.split(" | ")[0].strip("| `"): line
        for line in lines
        if line.startswith("| `")
    }


def test_an_old_run_json_is_the_record_of_every_part():
    run = results(WHOLE, core=True, training=True, sizes=True)
    table = rows(provenance_lines(run))
    assert set(table) == {"core", "training", "sizes"}  # no results, no row
    for line in table.values():
        assert "2026-11-29 03:25:33 to 04:19:06 (whole run)" in line
        assert "`2be47cc`" in line and "1.17 / 3.04" in line
    assert "**Host:** AMD EPYC, 2 cores, 23.5 GiB RAM (Linux-6)." in provenance_lines(
        run
    )


def test_a_part_run_again_has_its_own_dates_commit_and_load():
    sizes = record("2026-12-02T10:00:00Z", "2026-12-02T10:00:03Z", "abc1234", 1.9, 2.4)
    training = record(
        "2026-12-01T23:50:00Z", "2026-12-02T01:10:00Z", "abc1234", 2.1, 3.5
    )
    run_json = {"parts": {"sizes": sizes, "training": training}, "whole_run": WHOLE}
    run = results(run_json, core=True, python=True, training=True, sizes=True)
    lines = "\n".join(provenance_lines(run)).splitlines()
    table = rows(lines)
    assert "(whole run)" in table["core"] and "`2be47cc`" in table["core"]
    assert "(whole run)" in table["python"]
    assert (
        "| `sizes` | 2026-12-02 10:00:00 to 10:00:03 | `abc1234` | 1.90 / 2.40 |"
        in lines
    )
    # A part across midnight keeps both dates.
    assert "2026-12-01T23:50:00Z to 2026-12-02T01:10:00Z" in table["training"]
    assert (
        "host" not in lines[lines.index(table["core"]) - 2]
    )  # one host: no host column
    text = "\n".join(machine_section(run))
    # One heading per record: the whole run's parts together, then each part's own.
    assert "### `core`, `python`: the whole run, 2026-11-29 03:25:33" in text
    assert "### `training`: 2026-12-01T23:50:00Z to" in text
    assert (
        "### `sizes`: 2026-12-02 10:00:00 to 10:00:03 (UTC), commit `abc1234`" in text
    )
    assert text.count("including 2.5 % steal") == 3


def test_new_layout_without_a_whole_run_and_a_quick_part_on_another_host():
    run_json = {
        "parts": {
            "core": record(
                "2026-12-03T08:00:00Z", "2026-12-03T08:05:00Z", "def5678", 1.0, 1.2
            ),
            "sizes": record(
                "2026-12-03T09:00:00Z",
                "2026-12-03T09:00:01Z",
                "def5678",
                1.0,
                1.0,
                16,
                True,
            ),
        }
    }
    run = results(run_json, core=True, server=True, sizes=True)
    lines = "\n".join(provenance_lines(run)).splitlines()
    table = rows(lines)
    assert set(table) == {"core", "sizes"}  # server: results but no record, no row
    assert "(**quick**)" in table["sizes"]
    assert any(
        line.startswith("| part | measured | commit | load mean/max | host |")
        for line in lines
    )
    assert "16 cores" in table["sizes"] and "2 cores" in table["core"]
    assert "whole run" not in "\n".join(machine_section(run))


def test_no_run_json():
    assert "no record" in provenance_lines(results(None, core=True))[0]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--only", "core,bogus"], "unknown part 'bogus'"),
        (["--only"], "--only needs a list of parts"),
        (["--only", ","], "--only names no part"),
        (["--max-runners", "two"], "--max-runners takes a positive number"),
        (["--fast"], "unknown argument: --fast"),
    ],
)
def test_run_sh_refuses_what_it_does_not_know(args, message):
    done = subprocess.run(
        ["bash", str(ROOT / "bench/run.sh"), *args],
        check=False,
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert done.returncode == 2
    assert message in done.stderr and "usage: bench/run.sh" in done.stderr
