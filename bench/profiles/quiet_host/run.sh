#!/usr/bin/env bash
# Issue 24's measurements on a second, quiet host: ESAPPO / PPO wall-clock with
# bench/python/training_overhead.py (1 env, then 8 envs, one job at a time, nothing else
# running), then step_parts.py and py-spy profiles of PPO and ESAPPO in-process at 1 env.
#
# Usage (from the repository root, with esa_client, stable-baselines3, gymnasium[mujoco] and
# py-spy importable, and ESA_SERVER_BIN naming an esa-server binary):
#     bench/profiles/quiet_host/run.sh OUTDIR
set -euo pipefail
out=${1:?usage: run.sh OUTDIR}
mkdir -p "$out"
PY=${PY:-python3}
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 PYTHONUNBUFFERED=1
{ uname -a; echo "cpus: $(OMP_NUM_THREADS= nproc)"; grep -m1 "model name" /proc/cpuinfo; cat /proc/loadavg; } | tee "$out/host.txt"
(while true; do cut -d' ' -f1-3 /proc/loadavg; sleep 10; done) >"$out/loadavg.txt" &
sampler=$!
trap 'kill $sampler' EXIT
train=bench/python/training_overhead.py
agents=(--agents ESAPPO --engines inprocess,sidecar)
"$PY" $train "${agents[@]}" --n-envs 1 --repeats 7 --out "$out/esappo_1env.json" | tee "$out/esappo_1env.log"
"$PY" $train "${agents[@]}" --n-envs 8 --ppo-n-steps 256 --repeats 5 --out "$out/esappo_8env.json" \
  | tee "$out/esappo_8env.log"
"$PY" bench/profiles/step_parts.py --repeats 2 | tee "$out/step_parts.md"
for agent in PPO ESAPPO; do
  py-spy record --format raw -r 250 -o "$out/$agent.txt" -- \
    "$PY" bench/profiles/run_one.py --agent $agent --engine inprocess --n-envs 1
  gzip -f "$out/$agent.txt"
done
