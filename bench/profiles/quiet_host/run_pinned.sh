#!/usr/bin/env bash
# Issue 24 on a quiet many-core host, in one go: five jobs side by side, each pinned to two
# cores of its own (a 2-core machine apiece, with nothing else on it), torch on one thread:
#   parts        step_parts.py: PPO, an A/A PPO, ESAPPO unfitted, gate closed and shipped
#   parts_avx2   the same with torch's, MKL's and oneDNN's kernels held to AVX2: does the
#                head's vectorised work slow the rest of the process (AVX-512 clocks)?
#   esappo_1env  training_overhead.py's ESAPPO rows, 1 env, in-process and native sidecar
#   esappo_8env  the same at 8 envs (256-step rollouts)
#   esappo_1env_avx2  the in-process 1-env row with the kernels held to AVX2
#
# Usage (from the repository root, with esa_client, stable-baselines3 and gymnasium[mujoco]
# importable, ESA_SERVER_BIN naming an esa-server binary, at least 10 cores):
#     bench/profiles/quiet_host/run_pinned.sh OUTDIR [REPEATS]
set -euo pipefail
out=${1:?usage: run_pinned.sh OUTDIR [REPEATS]}
repeats=${2:-9}
mkdir -p "$out"
PY=${PY:-python3}
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 PYTHONUNBUFFERED=1
{
  uname -a
  echo "cpus: $(OMP_NUM_THREADS= nproc)"
  grep -m1 "model name" /proc/cpuinfo
  grep -m1 -o 'avx512[a-z_]*' /proc/cpuinfo | head -1 || echo "no avx512"
  lscpu -e 2>/dev/null | head -20 || true
  cat /proc/loadavg
  "$PY" -c "import sys,torch,numpy;print(sys.version.split()[0],torch.__version__,numpy.__version__)"
} >"$out/host.txt" 2>&1
(while true; do cut -d' ' -f1-3 /proc/loadavg; sleep 10; done) >"$out/loadavg.txt" &
sampler=$!
trap 'kill $sampler 2>/dev/null' EXIT

avx2=(env ATEN_CPU_CAPABILITY=avx2 MKL_ENABLE_INSTRUCTIONS=AVX2 ONEDNN_MAX_CPU_ISA=AVX2)
# Runs "$@" on the two cores CORES (a,b) only; its children (the sidecar) inherit them.
pinned() {
  local cores=$1
  shift
  "$PY" -c 'import os, sys
os.sched_setaffinity(0, {int(c) for c in sys.argv[1].split(",")})
os.execvp(sys.argv[2], sys.argv[2:])' "$cores" "$@"
}
parts=(bench/profiles/step_parts.py --repeats 5
  --agents "PPO,PPO again,ESAPPO unfitted,ESAPPO gate closed,ESAPPO")
train=(bench/python/training_overhead.py --agents ESAPPO --repeats "$repeats")
pinned 0,1 "$PY" "${parts[@]}" >"$out/parts.md" 2>"$out/parts.err" &
pinned 2,3 "${avx2[@]}" "$PY" "${parts[@]}" >"$out/parts_avx2.md" 2>"$out/parts_avx2.err" &
pinned 4,5 "$PY" "${train[@]}" --engines inprocess,sidecar --n-envs 1 \
  --out "$out/esappo_1env.json" >"$out/esappo_1env.log" 2>&1 &
pinned 6,7 "$PY" "${train[@]}" --engines inprocess,sidecar --n-envs 8 --ppo-n-steps 256 \
  --out "$out/esappo_8env.json" >"$out/esappo_8env.log" 2>&1 &
pinned 8,9 "${avx2[@]}" "$PY" "${train[@]}" --engines inprocess --n-envs 1 \
  --out "$out/esappo_1env_avx2.json" >"$out/esappo_1env_avx2.log" 2>&1 &
wait_all=0
for job in $(jobs -p); do
  [[ $job == "$sampler" ]] && continue
  wait "$job" || wait_all=$?
done
exit $wait_all
