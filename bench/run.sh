#!/usr/bin/env bash
# The benchmark run behind `make bench`: core criterion bench, the Rust load generator (each
# row beside a bare tonic echo), the Python client bench (beside a bare grpcio echo), the
# training-overhead bench, the RLlib scaling bench (PPO and SAC, 1 to 8 env runners, with ESA
# in each runner, on one server and on Zenoh shards) and the artifact sizes, then
# bench/report.py writes BENCHMARKS.md and bench/results/latency_vs_batch.png. Everything
# stays on loopback.
#
# Usage: bench/run.sh [--quick] [--only PARTS] [--max-runners N]
#   --only PARTS: run only these parts (comma-separated) and keep the others' results in
#     bench/results/; the parts, named as their result files, in the order they run:
#       core           cargo bench -p esa-core --bench pair          -> core.json
#       server         esa-bench, the Rust load generator            -> server.json
#       python         client_latency.py                             -> python.json, section_1b.json
#       training       training_overhead.py                          -> training.json
#       rllib_scaling  rllib_scaling.py                              -> rllib_scaling.json
#       sizes          artifact_sizes.py                             -> sizes.json
#     Without it, every part.
#   --max-runners N: the RLlib scaling bench's largest number of env runners (of 1, 2, 4, 8;
#     default 8). Above the host's cores the rows are CPU-bound.
#   --quick: short windows for a smoke test; the results still go to bench/results/,
#     so do not commit a quick run.
#
# Each part that runs gets its own record in bench/results/run.json, under "parts": its
# start and end, the commit, the load average sampled during it (min/mean/max), the CPU time
# of all cores (steal included), the host and its commands. The other parts keep theirs; a
# part without a record of its own (results of a run.sh that wrote one record for the whole
# run) keeps that run's record, kept as "whole_run". bench/report.py says per part when, at
# which commit and under which load it was measured.
set -euo pipefail
cd "$(dirname "$0")/.."

PARTS=(core server python training rllib_scaling sizes)
usage() {
  echo "usage: bench/run.sh [--quick] [--only PARTS] [--max-runners N]" >&2
  echo "  PARTS: comma-separated, of: ${PARTS[*]}" >&2
  [[ -n ${1:-} ]] && echo "bench/run.sh: $1" >&2
  exit 2
}

QUICK=false
ONLY=""
MAX_RUNNERS=""
while [[ $# -gt 0 ]]; do
  case $1 in
    --quick) QUICK=true ;;
    --only) [[ $# -ge 2 ]] || usage "--only needs a list of parts"; ONLY=$2; shift ;;
    --only=*) ONLY=${1#--only=} ;;
    --max-runners) [[ $# -ge 2 ]] || usage "--max-runners needs a number"; MAX_RUNNERS=$2; shift ;;
    --max-runners=*) MAX_RUNNERS=${1#--max-runners=} ;;
    *) usage "unknown argument: $1" ;;
  esac
  shift
done
if [[ -n $MAX_RUNNERS && ! $MAX_RUNNERS =~ ^[1-9][0-9]*$ ]]; then
  usage "--max-runners takes a positive number, not '$MAX_RUNNERS'"
fi

# The parts to run, in the order of PARTS whatever the order given.
declare -A WANTED=()
if [[ -n $ONLY ]]; then
  IFS=, read -ra asked <<<"$ONLY"
  for name in "${asked[@]}"; do
    [[ -z $name ]] && continue
    [[ " ${PARTS[*]} " == *" $name "* ]] || usage "unknown part '$name'"
    WANTED[$name]=1
  done
  [[ ${#WANTED[@]} -gt 0 ]] || usage "--only names no part"
else
  for name in "${PARTS[@]}"; do WANTED[$name]=1; done
fi

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
if [[ -n $MAX_RUNNERS ]]; then
  RLLIB_ARGS+=(--max-runners "$MAX_RUNNERS")
fi

mkdir -p "$RESULTS"
RUN_JSON=$RESULTS/run.json
sampler=""
# The load sampler of the part running, stopped by its own PID.
trap '[[ -n $sampler ]] && kill "$sampler" 2>/dev/null; true' EXIT

commands=()
run() {
  commands+=("$*")
  echo "+ $*" >&2
  "$@"
}

# The binaries every part but sizes runs, and whose sizes sizes reports; a part's record
# lists this build among its commands.
run "$CARGO" build --release -p esa-server -p esa-bench
build_commands=("${commands[@]}")

part_core() {
  run "$CARGO" bench -p esa-core --bench pair -- --noplot "${CRITERION_ARGS[@]}"
  run "$PY" bench/report.py --snapshot-core "$RESULTS/core.json"
}
part_server() {
  run target/release/esa-bench --server "$ESA_SERVER_BIN" --json "$RESULTS/server.json" \
    "${BENCH_ARGS[@]}"
}
part_python() {
  run "$PY" bench/python/client_latency.py --out "$RESULTS/python.json" \
    --section-1b-out "$RESULTS/section_1b.json" "${PY_ARGS[@]}"
}
part_training() {
  run "$PY" bench/python/training_overhead.py --out "$RESULTS/training.json" "${TRAIN_ARGS[@]}"
}
part_rllib_scaling() {
  # Up to 8 env runners (--max-runners caps it); on a host with fewer cores the rows with many
  # runners are CPU-bound, and BENCHMARKS.md says so.
  run "$PY" bench/python/rllib_scaling.py --out "$RESULTS/rllib_scaling.json" "${RLLIB_ARGS[@]}"
}
part_sizes() {
  # The wheel and the binaries as the last builds left them (`make wheel` builds the wheel).
  run "$PY" bench/python/artifact_sizes.py --out "$RESULTS/sizes.json"
}

# Runs one part and writes its record into run.json, beside the other parts' records.
measure() {
  local part=$1 samples=$RESULTS/loadavg.$1.tmp.txt
  local started loadavg_start cpu_start finished loadavg_end cpu_end
  commands=("${build_commands[@]}")
  started=$(date -u +%FT%TZ)
  loadavg_start=$(cat /proc/loadavg)
  # On a VM the hypervisor's steal time slows every figure; its share is reported.
  cpu_start=$(grep '^cpu ' /proc/stat)
  (while true; do cut -d' ' -f1 /proc/loadavg; sleep "$LOAD_INTERVAL"; done) >"$samples" &
  sampler=$!
  "part_$part"
  finished=$(date -u +%FT%TZ)
  loadavg_end=$(cat /proc/loadavg)
  cpu_end=$(grep '^cpu ' /proc/stat)
  kill "$sampler" 2>/dev/null || true
  sampler=""
  "$PY" - "$RUN_JSON" "$part" "$samples" "$QUICK" "$started" "$finished" "$loadavg_start" \
    "$loadavg_end" "$LOAD_INTERVAL" "$cpu_start" "$cpu_end" "${commands[@]}" <<'PYEOF'
import json, os, platform, subprocess, sys
(run_json, part, samples_path, quick, started, finished, load_start, load_end, interval,
 cpu_start, cpu_end, *commands) = sys.argv[1:]
PARTS = ("core", "server", "python", "training", "rllib_scaling", "sizes")
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
samples = [float(x) for x in open(samples_path).read().split()]
if not samples:  # a part shorter than one interval: its start and end
    samples = [float(load_start.split()[0]), float(load_end.split()[0])]
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
record = {
    "cpu_model": lscpu.get("Model name", "?").strip(),
    "cores": os.cpu_count(),
    "ram_gib": mem_kib / 2**20,
    "kernel": platform.platform(),
    "started": started,
    "finished": finished,
    "commit": commit,
    "quick": quick == "true",
    "loadavg_start": load_start,
    "loadavg_end": load_end,
    "load_interval_s": int(interval),
    "loadavg": {
        "samples": len(samples),
        "min": min(samples),
        "mean": sum(samples) / len(samples),
        "max": max(samples),
    },
    "cpu_time_percent": cpu_share,
    "cpuidle": cpuidle,
    "commands": commands,
}
# run.json: {"parts": {part: record}, "whole_run": record}. A file of the old layout, one
# record for the whole run, becomes "whole_run": the record of the parts without their own.
try:
    old = json.load(open(run_json))
except FileNotFoundError:
    old = {}
if "parts" not in old:
    old = {"parts": {}, "whole_run": old} if old else {"parts": {}}
old["parts"][part] = record
old["parts"] = {p: old["parts"][p] for p in PARTS if p in old["parts"]}
if all(p in old["parts"] for p in PARTS):
    old.pop("whole_run", None)
tmp = run_json + ".tmp"
open(tmp, "w").write(json.dumps(old, indent=2))
os.replace(tmp, run_json)
print(f"{part}: {started} to {finished}, record in {run_json}", file=sys.stderr)
PYEOF
  rm -f "$samples"
}

for part in "${PARTS[@]}"; do
  if [[ -n ${WANTED[$part]:-} ]]; then
    measure "$part"
  fi
done
"$PY" bench/report.py
