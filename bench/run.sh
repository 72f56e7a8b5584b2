#!/usr/bin/env bash
# The whole benchmark run behind `make bench`: core criterion bench, the Rust load
# generator (each row beside a bare tonic echo), the Python client bench (beside a bare
# grpcio echo), the training-overhead bench, the RLlib scaling bench (PPO and SAC, 1 to 8 env
# runners, with ESA in each runner, on one server and on Zenoh shards), then bench/report.py
# writes BENCHMARKS.md and bench/results/latency_vs_batch.png. Everything stays on loopback.
#
# Usage: bench/run.sh [--quick]
#   --quick: short windows for a smoke test; the results still go to bench/results/,
#     so do not commit a quick run.
set -euo pipefail
cd "$(dirname "$0")/.."

QUICK=false
for arg in "$@"; do
  case $arg in
    --quick) QUICK=true ;;
    *) echo "usage: bench/run.sh [--quick]" >&2; exit 2 ;;
  esac
done

PY=${PY:-.venv/bin/python}
CARGO=${CARGO:-cargo}
RESULTS=bench/results
LOAD_INTERVAL=5
export ESA_SERVER_BIN=${ESA_SERVER_BIN:-$PWD/target/release/esa-server}
export MUJOCO_GL=${MUJOCO_GL:-egl}

if $QUICK; then
  CRITERION_ARGS=(--warm-up-time 0.5 --measurement-time 1)
  BENCH_ARGS=(--warmup 0.1 --window 0.3 --rss-sessions 20000)
  PY_ARGS=(--warmup 0.1 --window 0.3)
  TRAIN_ARGS=(--ppo-steps 4096 --sac-steps 1600 --sac-learning-starts 400 --repeats 1 --ppo-repeats 1)
  RLLIB_ARGS=(--quick)
else
  CRITERION_ARGS=(--warm-up-time 2 --measurement-time 4)
  BENCH_ARGS=()
  PY_ARGS=()
  TRAIN_ARGS=()
  RLLIB_ARGS=()
fi

mkdir -p "$RESULTS"
CORE_JSON=$RESULTS/core.json
RUN_JSON=$RESULTS/run.json
started=$(date -u +%FT%TZ)
loadavg_start=$(cat /proc/loadavg)
# On a VM the hypervisor's steal time slows every figure; its share is reported.
cpu_start=$(grep '^cpu ' /proc/stat)
# Samples the load for the report; stopped by its own PID at exit.
(while true; do cut -d' ' -f1 /proc/loadavg; sleep "$LOAD_INTERVAL"; done) >"$RESULTS/loadavg.tmp.txt" &
sampler=$!
trap 'kill "$sampler" 2>/dev/null || true' EXIT

commands=()
run() {
  commands+=("$*")
  echo "+ $*" >&2
  "$@"
}

run "$CARGO" build --release -p esa-server -p esa-bench
run "$CARGO" bench -p esa-core --bench pair -- --noplot "${CRITERION_ARGS[@]}"
run "$PY" bench/report.py --snapshot-core "$CORE_JSON"

run target/release/esa-bench --server "$ESA_SERVER_BIN" --json "$RESULTS/server.json" \
  "${BENCH_ARGS[@]}"
run "$PY" bench/python/client_latency.py --out "$RESULTS/python.json" \
  --section-1b-out "$RESULTS/section_1b.json" "${PY_ARGS[@]}"
run "$PY" bench/python/training_overhead.py --out "$RESULTS/training.json" "${TRAIN_ARGS[@]}"
# Up to 8 env runners (--max-runners caps it); on a host with fewer cores the rows with many
# runners are CPU-bound, and BENCHMARKS.md says so.
run "$PY" bench/python/rllib_scaling.py --out "$RESULTS/rllib_scaling.json" "${RLLIB_ARGS[@]}"
# The wheel and the binaries as the last builds left them (`make wheel` builds the wheel).
run "$PY" bench/python/artifact_sizes.py --out "$RESULTS/sizes.json"

finished=$(date -u +%FT%TZ)
loadavg_end=$(cat /proc/loadavg)
cpu_end=$(grep '^cpu ' /proc/stat)
kill "$sampler" 2>/dev/null || true
commands+=("$PY bench/report.py")
"$PY" - "$RESULTS" "$RUN_JSON" "$started" "$finished" "$loadavg_start" "$loadavg_end" \
  "$LOAD_INTERVAL" "$cpu_start" "$cpu_end" "${commands[@]}" <<'PYEOF'
import json, os, platform, subprocess, sys
results, run_json, started, finished, load_start, load_end, interval, cpu_start, cpu_end, *commands = sys.argv[1:]
# /proc/stat "cpu" fields: user nice system idle iowait irq softirq steal (jiffies).
fields = ["user", "nice", "system", "idle", "iowait", "irq", "softirq", "steal"]
spent = [int(b) - int(a) for a, b in zip(cpu_start.split()[1:9], cpu_end.split()[1:9])]
cpu_share = {name: 100 * x / max(sum(spent), 1) for name, x in zip(fields, spent)}
lscpu = dict(
    line.split(":", 1) for line in subprocess.run(
        ["lscpu"], capture_output=True, text=True, check=True
    ).stdout.splitlines() if ":" in line
)
mem_kib = next(int(l.split()[1]) for l in open("/proc/meminfo") if l.startswith("MemTotal:"))
samples = [float(x) for x in open(f"{results}/loadavg.tmp.txt").read().split()]
commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
def sysfs(path):
    try:
        return open(path).read().strip()
    except OSError:
        return None
# How long an idle core polls before it halts sets a round trip's wake-up latency on a VM.
cpuidle = {
    "driver": sysfs("/sys/devices/system/cpu/cpuidle/current_driver"),
    "governor": sysfs("/sys/devices/system/cpu/cpuidle/current_governor_ro"),
    "guest_halt_poll_ns": sysfs("/sys/module/haltpoll/parameters/guest_halt_poll_ns"),
}
run = {
    "cpu_model": lscpu.get("Model name", "?").strip(),
    "cores": os.cpu_count(),
    "ram_gib": mem_kib / 2**20,
    "kernel": platform.platform(),
    "started": started,
    "finished": finished,
    "commit": commit,
    "loadavg_start": load_start,
    "loadavg_end": load_end,
    "load_interval_s": int(interval),
    "loadavg": {
        "samples": len(samples),
        "min": min(samples, default=float("nan")),
        "mean": sum(samples) / len(samples) if samples else float("nan"),
        "max": max(samples, default=float("nan")),
    },
    "cpu_time_percent": cpu_share,
    "cpuidle": cpuidle,
    "commands": commands,
}
open(run_json, "w").write(json.dumps(run, indent=2))
PYEOF
rm -f "$RESULTS/loadavg.tmp.txt"
"$PY" bench/report.py
