#!/usr/bin/env bash
# `make soak`: builds esa-server and the load generator, runs esa-soak (a few
# minutes of load with floods and faults against the real server, everything on
# loopback) into bench/results/soak.json, then puts its summary into the soak
# section of BENCHMARKS.md. Arguments go to esa-soak (e.g. --seconds 60).
set -euo pipefail
cd "$(dirname "$0")/.."

PY=${PY:-.venv/bin/python}
CARGO=${CARGO:-cargo}

"$CARGO" build --release -p esa-server -p esa-bench
target/release/esa-soak --server target/release/esa-server --json bench/results/soak.json "$@"
"$PY" bench/soak_report.py --results bench/results/soak.json --out BENCHMARKS.md
