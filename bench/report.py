"""Writes BENCHMARKS.md and the latency-vs-batch PNG from the results of one ``bench/run.sh``.

Reads ``bench/results/``: ``server.json`` (esa-bench), ``python.json`` and ``section_1b.json``
(client_latency.py), ``training.json`` (training_overhead.py), ``sizes.json``
(artifact_sizes.py), ``run.json`` (machine, load and commands, written by run.sh) and
``core.json``, the medians of the core pair bench that run.sh copies out of criterion's
estimates (read from ``target/criterion`` when ``core.json`` is missing). Every target is
listed with its measured figure and PASS or MISS; every gRPC latency row stands beside the
same host's bare echo round trip (tonic for the Rust client, grpcio for Python).

Usage::

    python bench/report.py [--results bench/results] [--out BENCHMARKS.md]
    python bench/report.py --snapshot-core bench/results/core.json   # criterion -> JSON
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import matplotlib
import numpy as np
import tyro

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parents[1]
PLOT_NAME = "latency_vs_batch.png"
# The goal of a figure we report without a number to meet.
NO_TARGET = "(no target; reported)"
# Line style per API in the plot; the colour is the transport's.
API_STYLES = {"batch": "-", "stream": "--", "-": ":"}


@dataclass
class Target:
    """One performance target and what was measured for it."""

    name: str
    goal: str
    measured: str
    passed: bool | None  # None: could not be measured in this run


def load(path: Path) -> dict | None:
    """The JSON at ``path``, or None if that part of the run did not happen."""
    return json.loads(path.read_text()) if path.is_file() else None


# Criterion group of each law in the core pair bench (``core/benches/pair.rs``).
CORE_GROUPS = {"1": "probe_report_pair", "1b": "probe_report_pair_1b"}

Medians = dict[tuple[str, int], float]
"""Median ns per pair of one law of the core bench: ``{(clock, D): ns}``, clock wall or cpu."""


def criterion_medians(root: Path, group: str = CORE_GROUPS["1"]) -> Medians:
    """The medians of one criterion group of the core bench, from its estimates."""
    out = {}
    for clock in ("wall", "cpu"):
        for estimates in sorted(root.glob(f"{group}_{clock}/*/new/estimates.json")):
            dim = int(estimates.parent.parent.name)
            out[(clock, dim)] = json.loads(estimates.read_text())["median"]["point_estimate"]
    return out


def snapshot_core(criterion: Path, path: Path) -> None:
    """Writes both laws' medians from criterion's estimates to ``path`` (JSON)."""
    medians = {
        law: {
            clock: {
                str(dim): ns
                for (c, dim), ns in criterion_medians(criterion, group).items()
                if c == clock
            }
            for clock in ("wall", "cpu")
        }
        for law, group in CORE_GROUPS.items()
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(
        json.dumps({"unit": "ns per pair (criterion median)", "medians": medians}, indent=2)
    )
    print(f"wrote {path}")


def core_medians(snapshot: dict | None, criterion: Path) -> dict[str, Medians]:
    """``{law: medians}`` from a ``core.json`` snapshot, else from criterion's estimates."""
    if snapshot is None:
        return {law: criterion_medians(criterion, group) for law, group in CORE_GROUPS.items()}
    return {
        law: {
            (clock, int(dim)): ns
            for clock, by_dim in snapshot["medians"].get(law, {}).items()
            for dim, ns in by_dim.items()
        }
        for law in CORE_GROUPS
    }


def table(header: list[str], rows: list[list[str]]) -> str:
    """A markdown table."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def find(rows: list[dict], **match: object) -> dict | None:
    """The first row whose fields equal ``match``."""
    return next((r for r in rows if all(r.get(k) == v for k, v in match.items())), None)


def fmt(value: float, digits: int = 1) -> str:
    """A number with thousands separators."""
    return f"{value:,.{digits}f}"


def verdict(target: Target) -> str:
    """PASS, MISS or n/a."""
    return {True: "PASS", False: "MISS", None: "n/a"}[target.passed]


def at_most(limit: float) -> Callable[[float], bool]:
    """A check that a figure is <= ``limit``."""
    return lambda x: x <= limit


MIB = 2**20

# Wall-clock of an ESA agent over its plain algorithm, per engine (the sidecar pays the
# round trips of a process boundary; "none" = the engine-free gradient controls). The
# off-policy algorithms' own gradient steps per env step dwarf ESA's step, so their budget is
# tighter.
TRAINING_LIMITS = {"inprocess": 1.15, "sidecar": 1.25, "none": 1.15}
OFF_POLICY_LIMIT = 1.10


def ratio_interval(row: dict) -> str:
    """The row's median ratio with a 95 % percentile-bootstrap interval of that median.

    A 1-env ratio moves by a few hundredths between runs; the interval says how far this
    run's median can be trusted. Seeded, so the report is the same for the same results.
    """
    ratios = np.asarray(row.get("ratios") or [row["ratio_median"]])
    text = f"{row['ratio_median']:.3f}"
    if len(ratios) < 3:
        return text
    draws = np.random.default_rng(0).choice(ratios, size=(10_000, len(ratios)))
    low, high = np.quantile(np.median(draws, axis=1), [0.025, 0.975])
    return f"{text} [{low:.2f}, {high:.2f}]"


# Rows priced for comparison, not held to a budget: ESAPPO with ESA on at every step of the
# run (no gate, no fade: what ESA costs while it acts) and its placebo (what it costs a user
# judging ESA on their task).
REFERENCE_ROWS = ("ESAPPO ungated [", "ESAPPO placebo [")


def training_limit(row: dict) -> float | None:
    """The wall-clock budget of one training-overhead row (None: a reference row)."""
    if row["esa"].startswith(REFERENCE_ROWS):
        return None
    if row["plain"] != "PPO":
        return OFF_POLICY_LIMIT
    return TRAINING_LIMITS[row["engine"]]


def size_targets(sizes: dict | None) -> list[Target]:
    """The client wheel (<= 10 MB), the server wheel and binaries (reported), ``sizes.json``."""
    sizes = sizes or {}
    out = []
    wheel = sizes.get("wheel")
    out.append(
        Target(
            "client wheel size (`make wheel`: esa_client and its extension)",
            "<= 10 MB",
            f"{wheel['bytes'] / 1e6:.1f} MB ({Path(wheel['path']).name})"
            if wheel
            else "not measured",
            wheel["bytes"] <= 10e6 if wheel else None,
        )
    )
    for key, what in [
        ("server_wheel", "server wheel `esa-server` (`esa-client[server]`)"),
        ("wheel_server", "esa-server executable in the server wheel"),
        ("wheel_extension", "extension `esa_client._native` in the wheel"),
        ("server_release", "esa-server binary, profile `release` (`make build`)"),
    ]:
        entry = sizes.get(key)
        out.append(
            Target(
                what,
                NO_TARGET,
                f"{entry['bytes'] / MIB:.1f} MiB" if entry else "not measured",
                None,
            )
        )
    return out


def targets(
    core: dict,
    server: dict | None,
    python: dict | None,
    training: dict | None,
    sizes: dict | None = None,
    section_1b: dict | None = None,
) -> list[Target]:
    """Every performance target with its measured figure."""
    out = size_targets(sizes)
    wall, cpu = core.get(("wall", 6)), core.get(("cpu", 6))
    out.append(
        Target(
            "core pair, D = 6 (criterion median, wall clock; on-CPU beside it)",
            "<= 100 ns",
            f"{fmt(wall)} ns wall, {fmt(cpu)} ns on-CPU" if wall and cpu else "not measured",
            wall <= 100 if wall else None,
        )
    )
    latency = server["latency"] if server else []
    single: list[tuple[str, str, str, float | None]] = [
        ("tcp", "unary", "Probe+Report over TCP", 100),
        ("uds", "unary", "Probe+Report over Unix socket", 60),
        ("zenoh", "unary", "Probe+Report queries over Zenoh", None),
        ("tcp", "stream", "StepStream over TCP", 60),
        ("uds", "stream", "StepStream over Unix socket", 60),
        ("zenoh", "stream", "StepStream queries over Zenoh", None),
    ]
    for socket, api, how, limit in single:
        row = find(latency, socket=socket, api=api, batch=1)
        echo = echo_words(row["p50_us"], echo_p50(row)) if row else ""
        out.append(
            Target(
                f"Rust client, 1 session, {how}, p50",
                NO_TARGET if limit is None else f"<= {limit:g} us",
                f"{fmt(row['p50_us'])} us (p99 {fmt(row['p99_us'])} us{echo})"
                if row
                else "not measured",
                row["p50_us"] <= limit if row and limit is not None else None,
            )
        )
    best_256 = max(
        (r for r in (server["throughput"] if server else []) if r["batch"] == 256),
        key=lambda r: r["session_steps_per_s"],
        default=None,
    )
    out.append(
        Target(
            "batched 256 x D = 6, session-steps/s (best transport)",
            ">= 1,000,000",
            (
                f"{fmt(best_256['session_steps_per_s'], 0)} ({best_256['socket']}/"
                f"{best_256['api']}, {best_256['concurrency']} clients)"
            )
            if best_256
            else "not measured",
            best_256["session_steps_per_s"] >= 1e6 if best_256 else None,
        )
    )
    py_rows = python["rows"] if python else []
    esa_8 = [r for r in py_rows if r["server"] == "esa-server" and r["envs"] == 8]
    zenoh_8 = [r for r in esa_8 if r["socket"] == "zenoh"]
    for label, candidates, limit in [
        ("Python SessionBatch(8) pair p50 (best transport)", esa_8, 250),
        ("Python SessionBatch(8) pair p50 over Zenoh (best api)", zenoh_8, None),
    ]:
        best_8 = min(candidates, key=lambda r: r["p50_us"], default=None)
        out.append(
            Target(
                label,
                NO_TARGET if limit is None else f"<= {limit} us",
                f"{fmt(best_8['p50_us'])} us ({best_8['socket']}/{best_8['api']})"
                if best_8
                else "not measured",
                best_8["p50_us"] <= limit if best_8 and limit is not None else None,
            )
        )
    in_process_8 = find(py_rows, server="esa-native", envs=8)
    out.append(
        Target(
            "Python SessionBatch(8) pair p50 in-process (`EsaClient.in_process()`)",
            "<= 10 us",
            f"{fmt(in_process_8['p50_us'])} us" if in_process_8 else "not measured",
            in_process_8["p50_us"] <= 10 if in_process_8 else None,
        )
    )
    step_8 = section_1b and find(section_1b["rows"], server="esa-native", envs=8, mode="step")
    out.append(
        Target(
            "Python SessionBatch(8) step p50 in-process (`SessionBatch.step` of ESAPPO's "
            "quadratic critic)",
            "<= 10 us",
            f"{fmt(step_8['p50_us'])} us" if step_8 else "not measured",
            step_8["p50_us"] <= 10 if step_8 else None,
        )
    )
    uds_8 = min((r for r in esa_8 if r["socket"] == "uds"), key=lambda r: r["p50_us"], default=None)
    out.append(
        Target(
            "Python SessionBatch(8) pair p50 over the Unix socket (best api)",
            "<= 150 us",
            f"{fmt(uds_8['p50_us'])} us ({uds_8['api']})" if uds_8 else "not measured",
            uds_8["p50_us"] <= 150 if uds_8 else None,
        )
    )
    for row in training["rows"] if training else []:
        envs = row.get("n_envs", training["args"].get("n_envs"))
        limit = training_limit(row)
        out.append(
            Target(
                f"{row['esa']} / {row['plain']} wall-clock ({row['steps']} steps, {envs} env(s))",
                f"<= {limit}" if limit is not None else NO_TARGET,
                ratio_interval(row),
                row["ratio_median"] <= limit if limit is not None else None,
            )
        )
    rss = server.get("rss") if server else None
    out.append(
        Target(
            f"RSS per idle session ({rss['sessions']:,} sessions, D = {rss['dim']})"
            if rss
            else "RSS per idle session",
            "<= 1 KiB",
            f"{fmt(rss['idle_bytes_per_session'], 0)} B" if rss else "not measured",
            rss["idle_bytes_per_session"] <= 1024 if rss else None,
        )
    )
    return out


def echo_p50(row: dict) -> float | None:
    """The p50 of a row's echo floor (esa-bench: ``echo``; Python: ``echo_p50_us``), if any."""
    echo = row.get("echo")
    return echo["p50_us"] if echo else row.get("echo_p50_us")


def echo_words(p50: float, echo: float | None) -> str:
    """``; 2.1x the echo`` for a target's measured figure, or nothing without an echo."""
    return f"; {p50 / echo:.1f}x the echo's {fmt(echo)} us" if echo else ""


def echo_cells(row: dict) -> list[str]:
    """A latency table's echo p50 and the row's p50 over it ("-" without an echo)."""
    echo = echo_p50(row)
    return [fmt(echo), f"{row['p50_us'] / echo:.1f}x"] if echo else ["-", "-"]


ECHO_HEADER = ["echo p50 us", "p50 / echo"]
ECHO_WORDS = (
    "`echo` = the same pair of requests (their sizes) sent by the same client library to a "
    "bare server that returns the bytes it gets, on the same kind of socket in the same run: "
    "the host's floor for a gRPC round trip, against which a row's ratio holds across hosts "
    "(none in-process or over Zenoh; not measured where `-`). The echo pair is two unary "
    "calls, so a StepStream row, whose messages open no new HTTP/2 stream, can go below it."
)


def plot(server: dict | None, python: dict | None, path: Path) -> None:
    """Pair latency (p50, band to p90) vs batch size, per transport; Rust and Python clients.

    One colour per transport (server and socket, the same in both panels), one line
    style per API.
    """
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8), sharey=True)
    panels = [
        (axes[0], "Rust client (esa-bench), D = 6", server["latency"] if server else [], "batch"),
        (axes[1], "Python SessionBatch, D = 6", python["rows"] if python else [], "envs"),
    ]
    colors: dict[str, str] = {}
    palette = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, title, rows, size in panels:
        series: dict[tuple[str, str], list[dict]] = {}
        for row in rows:
            if row.get("api") == "unary":
                continue
            transport = "/".join(str(row[k]) for k in ("server", "socket") if k in row)
            series.setdefault((transport, row["api"]), []).append(row)
        for (transport, api), points in sorted(series.items()):
            # esa-server's rows of both panels share a colour per socket.
            key = transport.removeprefix("esa-server/")
            color = colors.setdefault(key, palette[len(colors) % len(palette)])
            points.sort(key=lambda r: r[size])
            x = [p[size] for p in points]
            line = ax.plot(
                x,
                [p["p50_us"] for p in points],
                marker="o",
                color=color,
                linestyle=API_STYLES.get(api, "-"),
                label=f"{transport}/{api}",
            )[0]
            ax.fill_between(
                x,
                [p["p50_us"] for p in points],
                [p["p90_us"] for p in points],
                color=line.get_color(),
                alpha=0.1,
            )
        ax.set_xscale("log", base=2)
        sizes = sorted({row[size] for row in rows})
        ax.set_xticks(sizes, [str(n) for n in sizes])
        ax.set_yscale("log")
        ax.set_xlabel("sessions per pair (batch size)")
        ax.set_title(title)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
    axes[0].set_ylabel("probe + report pair latency, us (line p50, band to p90)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def server_sections(server: dict) -> list[str]:
    """Markdown for the esa-bench results."""
    bounds = server["bounds"]
    lines = [
        "## Server, from the Rust load generator (`esa-bench`)",
        "",
        f"Sessions of D = {server['dim']}; load generator on {server['client_threads']} tokio "
        f"thread(s), the server with its default runtime (one worker per core). Each "
        f"measurement: {bounds['warmup']['secs'] + bounds['warmup']['nanos'] / 1e9:g} s "
        f"warm-up, then at most {bounds['window']['secs'] + bounds['window']['nanos'] / 1e9:g} s "
        f"or {bounds['max_pairs']:,} pairs. A pair = probe + report round trips; `unary` = "
        "`Probe`+`Report` (one session), `batch` = `ProbeBatch`+`ReportBatch` calls, "
        "`stream` = both on one `StepStream`. `zenoh` = the server with `--zenoh` on its "
        "loopback listener and a Zenoh peer in the load generator: one query per call, and "
        "per StepStream message, on `esa/v1/<RpcName>` (Zenoh runs its own threads in both "
        "processes, beside the tokio threads counted here). "
        + ECHO_WORDS.replace("the same client library", "tonic"),
        "",
        "### Pair latency, one client",
        "",
    ]
    rows = [
        [
            r["socket"],
            r["api"],
            str(r["batch"]),
            fmt(r["p50_us"]),
            fmt(r["p90_us"]),
            fmt(r["p99_us"]),
            fmt(r["mean_us"]),
            f"{r['pairs']:,}",
            *echo_cells(r),
        ]
        for r in server["latency"]
    ]
    header = ["socket", "api", "batch", "p50 us", "p90 us", "p99 us", "mean us", "pairs"]
    lines.append(table(header + ECHO_HEADER, rows))
    if not any(r["socket"] == "zenoh" for r in server["latency"]):
        lines += ["", "Zenoh: not measured in this run."]
    lines += ["", "### Throughput, concurrent clients", ""]
    rows = [
        [
            r["socket"],
            r["api"],
            str(r["batch"]),
            str(r["concurrency"]),
            fmt(r["session_steps_per_s"], 0),
            f"{r['pairs']:,}",
            fmt(r["seconds"], 2),
        ]
        for r in server["throughput"]
    ]
    lines.append(
        table(["socket", "api", "batch", "clients", "session-steps/s", "pairs", "seconds"], rows)
    )
    rss = server.get("rss")
    if rss:
        lines += [
            "",
            "### Memory",
            "",
            f"A fresh server (TCP), VmRSS from `/proc/<pid>/status`: {rss['before_kib']:,} KiB "
            f"with one session created and closed; {rss['idle_kib']:,} KiB with "
            f"{rss['sessions']:,} idle sessions of D = {rss['dim']} "
            f"(**{fmt(rss['idle_bytes_per_session'], 0)} B per session**); "
            f"{rss['stepped_kib']:,} KiB after one probe + report on each "
            f"({fmt(rss['stepped_bytes_per_session'], 0)} B per session).",
        ]
    return lines


def python_section(python: dict) -> list[str]:
    """Markdown for the Python client results."""
    args = python["args"]
    lines = [
        "## Python client (`SessionBatch`)",
        "",
        f"One pair = `batch.probe(actions)` + `-|probe|^2` + `batch.report(q)`, D = {args['dim']}; "
        f"{args['warmup']:g} s warm-up, then at most {args['window']:g} s or "
        f"{args['max_pairs']:,} pairs. `batch` = ProbeBatch/ReportBatch calls "
        "(`use_stream=False`, the default), `stream` = the StepStream. `uds` is "
        '`EsaClient.spawn()`, what the SB3 drop-ins use with `esa_engine="sidecar"`; '
        "`esa-native` = `EsaClient.in_process()` (esa-core in-process, their default). "
        '`zenoh` = `EsaClient.spawn(transport="zenoh")` (esa-server `--zenoh` on '
        "loopback): queries on `esa/v1/ProbeBatch`/`ReportBatch` (`batch` and `stream` "
        "alike: a Zenoh query is one message already). "
        + ECHO_WORDS.replace("the same client library", "grpcio (`bench/python/echo_server.py`)"),
        "",
    ]
    rows = [
        [
            r["server"],
            r["socket"],
            r["api"],
            str(r["envs"]),
            fmt(r["p50_us"]),
            fmt(r["p99_us"]),
            fmt(r["session_steps_per_s"], 0),
            *echo_cells(r),
        ]
        for r in python["rows"]
    ]
    header = ["server", "socket", "api", "envs", "p50 us", "p99 us", "session-steps/s"]
    lines.append(table(header + ECHO_HEADER, rows))
    return lines


def repeat_words(args: dict) -> str:
    """How a training run took its turns."""
    return (
        f"{args['ppo_repeats']} repeats of PPO's pairs and {args['repeats']} of SAC's and "
        f"TD3's, family by family, after {args['warmup_runs']} short untimed run(s) of every "
        "agent; a family's plain agent and its ESA agents train side by side, one at a time, "
        f"each handing the turn to the next after {args['slice_s']} s (round-robin, reversed "
        "every other repeat), and an agent's time is the sum of its turns, so a drift of the "
        "host's speed falls on all of them alike"
    )


def training_section(training: dict) -> list[str]:
    """Markdown for the training-overhead results."""
    args = training["args"]
    lines = [
        "## Training overhead",
        "",
        f"{args['env_id']}, {args['n_envs']} env(s) (DummyVecEnv; 1 is SB3's default), seed "
        f"{args['seed']}, torch on one thread, SB3 defaults except PPO "
        f"`n_steps={args['ppo_n_steps']}`, `batch_size=64` and SAC "
        f"`learning_starts={args['sac_learning_starts']}` (TD3 too); ESA agents with their "
        "family's shipped default (`EsaConfig.ppo()`, `EsaConfig.off_policy()`; the gate keeps "
        "ESA off while the critic is poor, and ESAPPO's fades it out by half the budget), with "
        "the same at `gate=None` (and ESAPPO's at `fade=None`: ESA at every step once a critic "
        'exists), the placebo (`esa_control="placebo"`) and the gradient control '
        '(`esa_control="gradient"`, `[none]`: no engine), each ESC agent on every '
        "engine (`esa_engine`): `[inprocess]` = esa-core in the trainer's process, `[sidecar]` = a "
        "private esa-server on a Unix socket (`EsaClient.spawn()`) through the Rust client of "
        "`esa_client._native` (its StepStream, one pipelined round trip per step). "
        f"PPO rollouts of `n_steps={args['ppo_n_steps']}` per env. Wall-clock "
        f"of `learn()`, {repeat_words(args)}; "
        "ratio = median of the "
        "per-repeat ratios, with a 95 % percentile-bootstrap interval of that median in "
        "brackets (10,000 resamples of the pairs; 3 pairs or more). The verdict is the "
        "median's.",
        "",
    ]
    rows = []
    for r in training["rows"]:
        split = r.get("esa_buckets") or [{}]

        def mean(bucket: str, split: list[dict] = split) -> float:
            return sum(b.get(bucket, 0.0) for b in split) / len(split)

        esa_mean = sum(r["esa_seconds"]) / len(r["esa_seconds"])
        plain_mean = sum(r["plain_seconds"]) / len(r["plain_seconds"])
        rows.append(
            [
                f"{r['esa']} / {r['plain']}",
                str(r.get("n_envs", args["n_envs"])),
                f"{r['steps']:,}",
                ", ".join(fmt(s, 2) for s in r["plain_seconds"]),
                ", ".join(fmt(s, 2) for s in r["esa_seconds"]),
                ratio_interval(r),
                fmt(mean("round_trips"), 2),
                fmt(mean("esa_step"), 2),
                fmt(mean("critic_fit"), 2),
                f"{(esa_mean - mean('round_trips')) / plain_mean:.2f}",
            ]
        )
    header = ["pair", "envs", "steps", "plain s", "ESA s", "ratio", "round trips s"]
    header += ["ESA step s", "critic fit s", "ratio without round trips"]
    lines += [
        table(header, rows),
        "",
        "Split of the ESA agents' time (mean over repeats): `round trips` = inside "
        "`SessionBatch.probe_applied` (which carries the previous step's deferred report) and "
        "`.flush` (client, network, server); `ESA step` = the whole `EsaRuntime.step` (round "
        "trips, the critic at the probes and applied actions, and on one step in eight at the "
        "sampled actions for the `esa/improvement` statistic); `critic fit` = ESAPPO's "
        "advantage-head fit and gate check. `ratio without round trips` = (ESA s - round trips "
        "s) / plain s: what the agent would cost with a free service.",
    ]
    return lines


def core_table(laws: dict[str, Medians]) -> str:
    """One row per D: wall and on-CPU ns of section 1's law, and of 1b's where measured."""
    with_1b = bool(laws.get("1b"))
    header = ["D", "wall ns", "on-CPU ns"]
    if with_1b:
        header = ["D", "section 1 wall ns", "1b wall ns", "section 1 on-CPU ns", "1b on-CPU ns"]
    rows = []
    for d in sorted({d for medians in laws.values() for _, d in medians}):

        def cell(law: str, clock: str, d: int = d) -> str:
            value = laws.get(law, {}).get((clock, d))
            return fmt(value) if value is not None else "-"

        if with_1b:
            rows.append(
                [str(d), cell("1", "wall"), cell("1b", "wall"), cell("1", "cpu"), cell("1b", "cpu")]
            )
        else:
            rows.append([str(d), cell("1", "wall"), cell("1", "cpu")])
    return table(header, rows)


def core_section(laws: dict[str, Medians]) -> list[str]:
    """Markdown for the criterion core bench."""
    lines = [
        "## Core (`cargo bench -p esa-core --bench pair`)",
        "",
        "One probe + report through `esa_core::Session` (criterion median per pair).",
    ]
    if laws.get("1b"):
        lines[-1] += (
            " `1b` = every CONTRACT.md section 1b field on (see the section 1b part below)."
        )
    return lines + ["", core_table(laws)]


def host_lines(run: dict | None) -> list[str]:
    """The one host every figure on the page was measured on, and when."""
    if not run:
        return ["**Host:** unknown (run.json missing: run `bench/run.sh`)."]
    return [
        f"**Host:** {run['cpu_model']}, {run['cores']} cores, {run['ram_gib']:.1f} GiB RAM "
        f"({run['kernel']}). **Run:** {run['started']} to {run['finished']} (UTC) at commit "
        f"`{run['commit']}`; load and commands under Machine and run, below."
    ]


def machine_lines(run: dict) -> list[str]:
    """The run's load and CPU-time shares (the host is named once, at the top)."""
    load = run["loadavg"]
    lines = [
        f"- Load average (1 min) sampled every {run['load_interval_s']} s during the run: "
        f"min {load['min']:.2f}, mean {load['mean']:.2f}, max {load['max']:.2f} "
        f"({load['samples']} samples); at start `{run['loadavg_start']}`, "
        f"at end `{run['loadavg_end']}`",
    ]
    share = run.get("cpu_time_percent")
    if share:
        busy = 100 - share["idle"] - share["iowait"]
        lines.append(
            f"- CPU time of both cores over the run (`/proc/stat`): {busy:.0f} % busy, "
            f"including {share['steal']:.1f} % steal (time the hypervisor gave other guests "
            f"while this one wanted to run); user {share['user']:.0f} %, "
            f"system {share['system']:.0f} %, idle {share['idle']:.0f} %"
        )
    idle = run.get("cpuidle")
    if idle and idle.get("driver"):
        polling = idle.get("guest_halt_poll_ns")
        lines.append(
            f"- CPU idle (`/sys/devices/system/cpu/cpuidle`): driver {idle['driver']}, governor "
            f"{idle['governor']}"
            + (f", guest halt polling {polling} ns" if polling is not None else "")
            + ". How long an idle core polls before it halts sets the wake-up latency that the"
            " round-trip rows measure"
        )
    return lines


def machine_section(run: dict | None) -> list[str]:
    """Markdown for the machine, the load and the commands."""
    if not run:
        return ["## Machine", "", "(run.json missing: run `bench/run.sh`)"]
    lines = ["## Machine and run", "", *machine_lines(run)]
    lines += [
        "",
        "Commands (`bench/run.sh`, what `make bench` runs):",
        "",
        "```",
        *run["commands"],
        "```",
    ]
    return lines


def ratio_text(value: float, base: float) -> str:
    """``value / base`` as ``1.23x``."""
    return f"{value / base:.2f}x"


def section_1b_section(python: dict, laws: dict[str, Medians]) -> list[str]:
    """Markdown for CONTRACT.md section 1b: the core pair and the Python step, 1b against 1."""
    args = python["args"]
    lines = [
        "## CONTRACT.md section 1b: the cost of the additions, and the pipelined step",
        "",
        "Section 1b's law with every field on (`normalize_response`, `shift_leak = 0.005`, "
        "`trust_region = 1`, as `EsaConfig()` sets them), an action scale sent with every "
        "probe and a `q_reference` with every report, against section 1's law in the same "
        "run.",
        "",
    ]
    if laws.get("1b"):
        lines += [
            "### Core pair",
            "",
            "One probe + report through `esa_core::Session` (criterion median per pair). "
            "The 1b pair also reads Algorithm 1's applied action after the probe (as the "
            "server does for every `ProbeResponse`) and reports Q there as the reference.",
            "",
            core_table(laws),
            "",
        ]
        extra = [
            f"D = {d}: +{fmt(laws['1b'][('cpu', d)] - laws['1'][('cpu', d)])} ns on-CPU "
            f"({ratio_text(laws['1b'][('cpu', d)], laws['1'][('cpu', d)])})"
            for d in sorted({d for _, d in laws["1b"]})
            if ("cpu", d) in laws["1"] and ("cpu", d) in laws["1b"]
        ]
        if extra:
            lines += ["Section 1b over section 1: " + "; ".join(extra) + ".", ""]
    lines += [
        "### Python `SessionBatch`",
        "",
        f"D = {args['dim']}, {args['warmup']:g} s warm-up, then at most {args['window']:g} s "
        f"or {args['max_pairs']:,} steps per row. `law 1, pair` = `probe` + `-|probe|^2` + "
        "`report` (the table of the Python client section). `law 1b, pair` = "
        "`probe_applied(actions, action_scales=0.3)` + the critic at the probes and the "
        "applied actions in one batch + `report(q, q_references=...)`: two round trips. "
        "`law 1b, pipelined` = the same with `report(..., defer=True)`: the report is sent "
        "with the next step's probe, one round trip per step on the StepStream. `batch` = "
        "ProbeBatch/ReportBatch calls, where pipelining would still be two round trips "
        "(not measured); `reference` = in-process. Time is per env step of all N envs.",
        "",
    ]
    rows = python["rows"]
    body = []
    for r in rows:
        base = find(
            rows,
            server=r["server"],
            socket=r["socket"],
            api=r["api"],
            envs=r["envs"],
            law="1",
            mode="pair",
        )
        body.append(
            [
                r["server"],
                r["socket"],
                r["api"],
                str(r["envs"]),
                r["law"],
                r["mode"],
                fmt(r["p50_us"]),
                fmt(r["p99_us"]),
                fmt(r["session_steps_per_s"], 0),
                ratio_text(r["p50_us"], base["p50_us"]) if base else "-",
                *echo_cells(r),
            ]
        )
    header = ["server", "socket", "api", "envs", "law", "mode", "p50 us", "p99 us"]
    header += ["session-steps/s", "p50 vs law 1 pair", *ECHO_HEADER]
    lines.append(table(header, body))
    summary = []
    for r in rows:
        if r["mode"] != "pipelined" or r["server"] != "esa-server":
            continue
        pair = find(
            rows,
            server=r["server"],
            socket=r["socket"],
            api=r["api"],
            envs=r["envs"],
            law="1b",
            mode="pair",
        )
        if pair:
            summary.append(
                f"- {r['socket']}/{r['api']}, N = {r['envs']}: pipelined step p50 "
                f"{fmt(r['p50_us'])} us against {fmt(pair['p50_us'])} us for the 1b pair "
                f"({ratio_text(r['p50_us'], pair['p50_us'])})"
            )
    if summary:
        lines += ["", "Pipelined step against the sequential pair (both section 1b):", ""]
        lines += summary
    return lines


@dataclass
class Args:
    """Writes BENCHMARKS.md and the latency plot from the results of one bench run."""

    results: Path = REPO_ROOT / "bench/results"
    """Folder of the run's JSON results (the plot goes there too)."""
    criterion: Path = REPO_ROOT / "target/criterion"
    """Criterion's output folder, for the core bench medians."""
    out: Path = REPO_ROOT / "BENCHMARKS.md"
    """The page to write."""
    snapshot_core: Path | None = None
    """Only write the core bench medians from ``criterion`` to this JSON file."""


def main(args: Args) -> None:
    """Reads the results and writes BENCHMARKS.md and the PNG."""
    if args.snapshot_core:
        snapshot_core(args.criterion, args.snapshot_core)
        return
    server = load(args.results / "server.json")
    python = load(args.results / "python.json")
    training = load(args.results / "training.json")
    run = load(args.results / "run.json")
    sizes = load(args.results / "sizes.json")
    laws = core_medians(load(args.results / "core.json"), args.criterion)
    core = laws["1"]
    section_1b = load(args.results / "section_1b.json")
    plot(server, python, args.results / PLOT_NAME)

    lines = [
        "# Benchmarks",
        "",
        "One `make bench` run (`bench/run.sh`), written by `bench/report.py` from its results "
        "in `bench/results/`; do not edit by hand. The performance targets first, then every "
        "measurement.",
        "",
        *host_lines(run),
        "",
        "## Targets",
        "",
        table(
            ["target", "goal", "measured", ""],
            [
                [t.name, t.goal, t.measured, verdict(t)]
                for t in targets(core, server, python, training, sizes, section_1b)
            ],
        ),
        "",
        "A training ratio is the median over repeated pairs, with a 95 % bootstrap interval "
        "of that median in brackets; the verdict is the median's (Training overhead, below).",
        "",
        f"![pair latency vs batch size](bench/results/{PLOT_NAME})",
        "",
    ]
    lines += machine_section(run) + [""]
    if core:
        lines += core_section(laws) + [""]
    if server:
        lines += server_sections(server) + [""]
    if python:
        lines += python_section(python) + [""]
    if training:
        lines += training_section(training) + [""]
    if section_1b:
        lines += section_1b_section(section_1b, laws) + [""]
    args.out.write_text("\n".join(lines))
    print(f"wrote {args.out} and {args.results / PLOT_NAME}")


if __name__ == "__main__":
    main(tyro.cli(Args))
