#!/bin/bash
# usage: prof_all.sh OUTDIR
set -u
cd "$(dirname "$0")/../.."
export OMP_NUM_THREADS=1
out=$1
for cfg in "PPO inprocess 1" "ESAPPO inprocess 1" "ESAPPO sidecar 1" "PPO inprocess 8" "ESAPPO inprocess 8" "ESAPPO sidecar 8"; do
  set -- $cfg
  name="$1-$2-$3env"; [ "$1" = PPO ] && name="PPO-$3env"
  nice -n 5 .venv/bin/py-spy record --format raw -r 250 -o "$out/$name.txt" -- \
    .venv/bin/python bench/profiles/run_one.py --agent $1 --engine $2 --n-envs $3 2>&1 | grep -v "^py-spy> You can"
done
