#!/usr/bin/env bash
# `make soak`: builds esa-server and esa-soak, runs the soak (a few minutes of load
# with floods and faults against the real server, everything on loopback) into
# tests/soak/results/soak.json, then the long fuzz run, and writes tests/soak/RESULTS.md.
# Arguments go to esa-soak (e.g. --seconds 60).
set -euo pipefail
cd "$(dirname "$0")/../.."

PY=${PY:-.venv/bin/python}
CARGO=${CARGO:-cargo}

"$CARGO" build --release -p esa-server -p esa-soak
target/release/esa-soak --server target/release/esa-server --json tests/soak/results/soak.json "$@"
# The long fuzz run (server/tests/fuzz.rs), recorded in soak.json for the report.
FUZZ_CASES=${ESA_SOAK_FUZZ_CASES:-1000000}
start=$(date +%s)
if ESA_FUZZ_CASES=$FUZZ_CASES "$CARGO" test --release -p esa-server --test fuzz; then
    fuzz_result=passed
else
    fuzz_result=FAILED
fi
"$PY" - "$FUZZ_CASES" "$fuzz_result" "$(( $(date +%s) - start ))" <<'PYEOF'
import json, sys
from pathlib import Path
path = Path("tests/soak/results/soak.json")
soak = json.loads(path.read_text())
soak["fuzz"] = {"cases": int(sys.argv[1]), "properties": 2, "result": sys.argv[2],
                "seconds": float(sys.argv[3])}
path.write_text(json.dumps(soak, indent=2) + "\n")
PYEOF
"$PY" tests/soak/report.py
[ "$fuzz_result" = passed ]
