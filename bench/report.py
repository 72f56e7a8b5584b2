"""Writes BENCHMARKS.md and the latency-vs-batch PNG from the results of ``bench/run.sh``.

Reads ``bench/results/``: ``run.json`` (per part: when, at which commit, on which host, under
which load and with which commands it ran; ``run.sh --only`` re-runs some parts and keeps the
others' results and records), ``core.json (the core pair
bench's criterion medians, copied out of ``target/criterion`` by ``--snapshot-core``),
``server.json`` (esa-bench), ``python.json`` and ``section_1b.json`` (client_latency.py),
``training.json`` (training_overhead.py), ``rllib_scaling.json`` (rllib_scaling.py) and
``sizes.json`` (artifact_sizes.py). A part the
run lacks is missing from the page, and its targets read "not measured".

Usage::

    python bench/report.py [--results bench/results] [--out BENCHMARKS.md]
    python bench/report.py --snapshot-core bench/results/core.json   # criterion -> JSON
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import matplotlib
import numpy as np
import tyro

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parents[1]
PLOT = "latency_vs_batch.png"
NO_TARGET = "(no target; reported)"
MIB = 2**20
# Criterion group of each law in the core pair bench (core/benches/pair.rs).
CORE_GROUPS = {"1": "probe_report_pair", "1b": "probe_report_pair_1b"}
CLOCKS = {"wall": "wall", "cpu": "on-CPU"}
# The sidecar pays the round trips of a process boundary; "none" = the engine-free gradient
# controls. The off-policy algorithms' own gradient steps dwarf ESA's step: a tighter budget.
TRAINING_LIMITS = {"inprocess": 1.15, "sidecar": 1.25, "none": 1.15}
OFF_POLICY_LIMIT = 1.10
# Priced for comparison, not held to a budget: the placebo (what judging ESA on a task costs).
# ESA on at every step (ungated) is held to the default's budget: what ESA costs while it acts.
REFERENCE_ROWS = ("ESAPPO placebo [",)
# The parts of a run (bench/run.sh's names, its result files' stems) -> the ``Run`` fields of
# their results.
PARTS = {
    "core": ("core",),
    "server": ("server",),
    "python": ("python", "section_1b"),
    "training": ("training",),
    "rllib_scaling": ("rllib_scaling",),
    "sizes": ("sizes",),
}
# training_overhead.py's timers of the ESA agents' time.
BUCKETS = {"round_trips": "round trips", "esa_step": "ESA step", "critic_fit": "critic fit"}

Column = tuple[str, Callable[[dict], str]]
"""A table column: its header and its cell's text for a row."""


def fmt(value: float | None, digits: int = 1) -> str:
    """A number with thousands separators; "-" for None."""
    return "-" if value is None else f"{value:,.{digits}f}"


def col(key: str, header: str | None = None, digits: int | None = None) -> Column:
    """The column of ``row[key]``, as text or as a number of ``digits`` decimals."""
    if digits is None:
        return header or key, lambda row: str(row[key])
    return header or key, lambda row: fmt(row.get(key), digits)


def table(rows: list[dict], columns: list[Column]) -> str:
    """The markdown table of ``rows``."""
    lines = ["| " + " | ".join(h for h, _ in columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(cell(row) for _, cell in columns) + " |" for row in rows]
    return "\n".join(lines)


def find(rows: list[dict], **match: object) -> dict | None:
    """The first row whose fields equal ``match``."""
    return next((r for r in rows if all(r.get(k) == v for k, v in match.items())), None)


LATENCY: list[Column] = [col("p50_us", "p50 us", 1), col("p99_us", "p99 us", 1)]
STEPS: Column = col("session_steps_per_s", "session-steps/s", 0)


GRPCIO: Column = col("grpcio_echo_p50_us", "grpcio echo p50 us", 1)
TONIC_WORDS = (
    "`tonic echo` = esa-bench's pair of requests of the same batch (their sizes) sent to a "
    "bare tonic server that returns the bytes it gets (`bench/src/echo.rs`: two unary calls, "
    "or two messages on one stream for `stream`), on the same kind of socket in the same run: "
    "the host's floor for these round trips, against which a row's ratio holds across hosts "
    "(none in-process or over Zenoh)."
)


def load(path: Path) -> dict | None:
    """The JSON at ``path``, or None where that part did not run."""
    return json.loads(path.read_text()) if path.is_file() else None


def criterion_medians(root: Path) -> dict[str, dict[str, dict[str, float]]]:
    """``{law: {clock: {D: ns}}}`` from criterion's estimates of the core pair bench."""
    out: dict = {law: {clock: {} for clock in CLOCKS} for law in CORE_GROUPS}
    for law, group in CORE_GROUPS.items():
        for clock in CLOCKS:
            for path in sorted(root.glob(f"{group}_{clock}/*/new/estimates.json")):
                median = json.loads(path.read_text())["median"]["point_estimate"]
                out[law][clock][path.parent.parent.name] = median
    return out


def ratio_interval(row: dict) -> str:
    """The median ratio with a 95 % percentile-bootstrap interval of that median.

    A 1-env ratio moves by a few hundredths between runs; the interval says how far this
    run's median can be trusted. Seeded, so the same results give the same page.
    """
    ratios = np.asarray(row["ratios"])
    text = f"{row['ratio_median']:.3f}"
    if len(ratios) < 3:
        return text
    draws = np.random.default_rng(0).choice(ratios, size=(10_000, len(ratios)))
    low, high = np.quantile(np.median(draws, axis=1), [0.025, 0.975])
    return f"{text} [{low:.2f}, {high:.2f}]"


def training_limit(row: dict) -> float | None:
    """The wall-clock budget of one training row (None: a reference row)."""
    if row["esa"].startswith(REFERENCE_ROWS):
        return None
    return TRAINING_LIMITS[row["engine"]] if row["plain"] == "PPO" else OFF_POLICY_LIMIT


@dataclass
class Run:
    """Everything one run wrote, keyed as ``bench/results/`` names it."""

    run: dict | None
    core: dict | None
    server: dict | None
    python: dict | None
    section_1b: dict | None
    training: dict | None
    sizes: dict | None
    rllib_scaling: dict | None = None

    def rows(self, part: str, key: str = "rows") -> list[dict]:
        """The rows of one part (none where it did not run)."""
        data = getattr(self, part)
        return data[key] if data else []

    def tonic_echo(self, row: dict) -> float | None:
        """The p50 of tonic's echo of the row's round trips (a Python row: at its batch)."""
        if "envs" in row:
            match = {"socket": row["socket"], "api": row["api"], "batch": row["envs"]}
            row = find(self.rows("server", "latency"), **match) or {}
        return (row.get("echo") or {}).get("p50_us")

    def over_echo(self, row: dict) -> str:
        """The row's p50 over tonic's echo, or "-" where there is none."""
        echo = self.tonic_echo(row)
        return f"{row['p50_us'] / echo:.1f}x" if echo else "-"

    def echo_columns(self) -> list[Column]:
        """The tonic echo's p50 and the row's over it."""
        return [
            ("tonic echo p50 us", lambda r: fmt(self.tonic_echo(r))),
            ("p50 / tonic echo", self.over_echo),
        ]

    def record(self, part: str) -> tuple[dict, bool] | None:
        """The run.json record of a part, and whether it is the part's own.

        run.json is ``{"parts": {part: record}, "whole_run": record}``; a part without a
        record of its own has the whole run's (and an older run.json, one record for the
        whole run, is that record).
        """
        data = self.run or {}
        parts, whole = (data["parts"], data.get("whole_run")) if "parts" in data else ({}, data)
        if part in parts:
            return parts[part], True
        return (whole, False) if whole else None

    def measured(self) -> list[tuple[str, dict, bool]]:
        """(part, record, own) of each part whose results are here and that has a record."""
        out = []
        for part, fields in PARTS.items():
            found = self.record(part)
            if found and any(getattr(self, field) for field in fields):
                out.append((part, *found))
        return out

    def core_ns(self, law: str, clock: str, dim: int) -> float | None:
        """The core pair's median ns."""
        return (self.core or {}).get("medians", {}).get(law, {}).get(clock, {}).get(str(dim))


def targets(run: Run) -> list[dict]:
    """Every performance target with its measured figure and verdict."""
    out = []

    def add(name: str, limit: float | None, unit: str, value: float | None, text, least=False):
        sign = ">=" if least else "<="
        passed = None
        if value is not None and limit is not None:
            passed = value >= limit if least else value <= limit
        out.append(
            {
                "target": name,
                "goal": NO_TARGET if limit is None else f"{sign} {limit:,}{unit}",
                "measured": "not measured" if value is None else text(),
                "": {True: "PASS", False: "MISS", None: "n/a"}[passed],
            }
        )

    sizes = run.sizes or {}
    wheel = sizes.get("wheel")
    add(
        "client wheel size (`make wheel`: esa_client and its extension)",
        10,
        " MB",
        wheel and wheel["bytes"] / 1e6,
        lambda: f"{wheel['bytes'] / 1e6:.1f} MB ({Path(wheel['path']).name})",
    )
    for key, what in [
        ("server_wheel", "server wheel `esa-server` (`esa-client[server]`)"),
        ("wheel_server", "esa-server executable in the server wheel"),
        ("wheel_extension", "extension `esa_client._native` in the wheel"),
        ("server_release", "esa-server binary, profile `release` (`make build`)"),
    ]:
        entry = sizes.get(key)
        add(what, None, "", entry and entry["bytes"], lambda e=entry: f"{e['bytes'] / MIB:.1f} MiB")
    wall, cpu = run.core_ns("1", "wall", 6), run.core_ns("1", "cpu", 6)
    add(
        "core pair, D = 6 (criterion median, wall clock; on-CPU beside it)",
        100,
        " ns",
        wall,
        lambda: f"{fmt(wall)} ns wall, {fmt(cpu)} ns on-CPU",
    )
    for socket, api, how, limit in [
        ("tcp", "unary", "Probe+Report over TCP", 100),
        ("uds", "unary", "Probe+Report over Unix socket", 60),
        ("zenoh", "unary", "Probe+Report queries over Zenoh", None),
        ("tcp", "stream", "StepStream over TCP", 60),
        ("uds", "stream", "StepStream over Unix socket", 60),
        ("zenoh", "stream", "StepStream queries over Zenoh", None),
    ]:
        row = find(run.rows("server", "latency"), socket=socket, api=api, batch=1)
        echo = row and run.tonic_echo(row)
        add(
            f"Rust client, 1 session, {how}, p50",
            limit,
            " us",
            row and row["p50_us"],
            lambda r=row, e=echo: (
                f"{fmt(r['p50_us'])} us (p99 {fmt(r['p99_us'])} us"
                + (f"; {run.over_echo(r)} tonic's echo, {fmt(e)} us)" if e else ")")
            ),
        )
    best = max(
        (r for r in run.rows("server", "throughput") if r["batch"] == 256),
        key=lambda r: r["session_steps_per_s"],
        default=None,
    )
    add(
        "batched 256 x D = 6, session-steps/s (best transport)",
        1_000_000,
        "",
        best and best["session_steps_per_s"],
        lambda: (
            f"{fmt(best['session_steps_per_s'], 0)} ({best['socket']}/{best['api']}, "
            f"{best['concurrency']} clients)"
        ),
        least=True,
    )
    esa_8 = [r for r in run.rows("python") if r["server"] == "esa-server" and r["envs"] == 8]
    for what, limit, candidates in [
        ("pair p50 (best transport)", 250, esa_8),
        ("pair p50 over Zenoh (best api)", None, [r for r in esa_8 if r["socket"] == "zenoh"]),
        (
            "pair p50 over the Unix socket (best api)",
            150,
            [r for r in esa_8 if r["socket"] == "uds"],
        ),
        ("pair p50 in-process (`EsaClient.in_process()`)", 10, esa_native(run.rows("python"))),
        (
            "step p50 in-process (`SessionBatch.step` of ESAPPO's quadratic critic)",
            10,
            [r for r in esa_native(run.rows("section_1b")) if r["mode"] == "step"],
        ),
    ]:
        row = min(candidates, key=lambda r: r["p50_us"], default=None)
        add(
            f"Python SessionBatch(8) {what}",
            limit,
            " us",
            row and row["p50_us"],
            lambda r=row: (
                f"{fmt(r['p50_us'])} us"
                + (f" ({r['socket']}/{r['api']})" if r["server"] == "esa-server" else "")
            ),
        )
    for row in run.rows("training"):
        add(
            f"{row['esa']} / {row['plain']} wall-clock ({row['steps']} steps, "
            f"{row['n_envs']} env(s))",
            training_limit(row),
            "",
            row["ratio_median"],
            lambda r=row: ratio_interval(r),
        )
    rss = run.server and run.server.get("rss")
    add(
        "RSS per idle session"
        + (f" ({rss['sessions']:,} sessions, D = {rss['dim']})" if rss else ""),
        1024,
        " B",
        rss and rss["idle_bytes_per_session"],
        lambda: f"{fmt(rss['idle_bytes_per_session'], 0)} B",
    )
    return out


def esa_native(rows: list[dict]) -> list[dict]:
    """The in-process rows at 8 envs."""
    return [r for r in rows if r["server"] == "esa-native" and r["envs"] == 8]


def plot(run: Run, path: Path) -> None:
    """Pair latency (p50, band to p90) against batch size: Rust client left, Python right.

    One colour per transport, the same in both panels, and one line style per api.
    """
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8), sharey=True)
    colors: dict[str, str] = {}
    palette = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, title, rows, size in [
        (axes[0], "Rust client (esa-bench)", run.rows("server", "latency"), "batch"),
        (axes[1], "Python SessionBatch", run.rows("python"), "envs"),
    ]:
        series: dict[tuple[str, str], list[dict]] = {}
        for row in rows:
            if row["api"] != "unary":
                transport = row.get("server", "esa-server").replace("esa-server", row["socket"])
                series.setdefault((transport, row["api"]), []).append(row)
        for (transport, api), points in sorted(series.items()):
            color = colors.setdefault(transport, palette[len(colors) % len(palette)])
            points.sort(key=lambda r: r[size])
            x, p50 = [p[size] for p in points], [p["p50_us"] for p in points]
            style = {"batch": "-", "stream": "--"}.get(api, ":")
            ax.plot(x, p50, marker="o", color=color, linestyle=style, label=f"{transport}/{api}")
            ax.fill_between(x, p50, [p["p90_us"] for p in points], color=color, alpha=0.1)
        sizes = sorted({row[size] for row in rows})
        ax.set_xscale("log", base=2)
        ax.set_xticks(sizes, [str(n) for n in sizes])
        ax.set_yscale("log")
        ax.set_xlabel("sessions per pair (batch size)")
        ax.set_title(f"{title}, D = 6")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
    axes[0].set_ylabel("probe + report pair latency, us (line p50, band to p90)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


HOST_KEYS = ("cpu_model", "cores", "ram_gib", "kernel")


def host_text(record: dict) -> str:
    """The host of a run.json record."""
    return (
        f"{record.get('cpu_model')}, {record.get('cores')} cores, "
        f"{fmt(record.get('ram_gib'))} GiB RAM ({record.get('kernel')})"
    )


def when(record: dict) -> str:
    """A record's start and end, the end's date left out where it is the start's."""
    start, end = (record.get(k) or "?" for k in ("started", "finished"))
    start_day, _, start_time = start.partition("T")
    end_day, _, end_time = end.partition("T")
    if start_time and end_time and start_day == end_day:
        return f"{start_day} {start_time.rstrip('Z')} to {end_time.rstrip('Z')}"
    return f"{start} to {end}"


def provenance_lines(runs: Run) -> list[str]:
    """The header's host(s), and when, at which commit and under which load each part ran."""
    measured = runs.measured()
    if not measured:
        return ["**Run:** no record of the run (`bench/results/run.json`)."]
    hosts = list(dict.fromkeys(host_text(record) for _, record, _ in measured))
    rows = []
    for part, record, own in measured:
        load = record.get("loadavg") or {}
        notes = [] if own else ["whole run"]
        if record.get("quick"):
            notes.append("**quick**")
        row = {
            "part": f"`{part}`",
            "measured": when(record) + (f" ({', '.join(notes)})" if notes else ""),
            "commit": f"`{record.get('commit')}`",
            "load mean/max": f"{fmt(load.get('mean'), 2)} / {fmt(load.get('max'), 2)}",
        }
        rows.append(row | {"host": host_text(record)})
    columns = [col(k) for k in ("part", "measured", "commit", "load mean/max")]
    lines = []
    if len(hosts) == 1:
        lines += [f"**Host:** {hosts[0]}.", ""]
    else:
        lines += ["**Hosts:** the parts ran on different hosts (column `host`).", ""]
        columns.append(col("host"))
    lines += [
        "**Runs:** each part as measured (UTC), the commit it ran at and the load average "
        "(1 min) sampled during it; `bench/run.sh --only PARTS` re-runs some parts and keeps "
        "the others' results. `whole run` = the part has no record of its own: the times and "
        "load are those of the whole `make bench` run it was part of (Machine and run, below).",
        "",
        table(rows, columns),
    ]
    return lines


def machine_section(runs: Run) -> list[str]:
    """Per record (one per part, or the whole run's): load, CPU time, idle states, commands."""
    groups: dict[int, tuple[dict, list[str], bool]] = {}
    for part, record, own in runs.measured():
        groups.setdefault(id(record), (record, [], own))[1].append(part)
    lines = ["## Machine and run"]
    for record, parts, own in groups.values():
        names = ", ".join(f"`{p}`" for p in parts)
        heading = f"{names}: " + ("" if own else "the whole run, ")
        lines += ["", f"### {heading}{when(record)} (UTC), commit `{record.get('commit')}`"]
        lines += record_lines(record)
    return lines


def record_lines(run: dict) -> list[str]:
    """One record's load, CPU time and idle states, and its commands."""
    load, share, idle = run["loadavg"], run["cpu_time_percent"], run["cpuidle"]
    lines = [
        "",
        f"- Host: {host_text(run)}"
        + (" (a `--quick` run: not figures of record)" if run.get("quick") else ""),
        f"- Load average (1 min) sampled every {run['load_interval_s']} s during it: "
        f"min {load['min']:.2f}, mean {load['mean']:.2f}, max {load['max']:.2f} "
        f"({load['samples']} samples); at start `{run['loadavg_start']}`, "
        f"at end `{run['loadavg_end']}`",
        f"- CPU time of all cores over it (`/proc/stat`): "
        f"{100 - share['idle'] - share['iowait']:.0f} % busy, including {share['steal']:.1f} % "
        "steal (time the hypervisor gave other guests while this one wanted to run); user "
        f"{share['user']:.0f} %, system {share['system']:.0f} %, idle {share['idle']:.0f} %",
    ]
    if idle["driver"]:
        polling = idle["guest_halt_poll_ns"]
        lines.append(
            f"- CPU idle (`/sys/devices/system/cpu/cpuidle`): driver {idle['driver']}, governor "
            f"{idle['governor']}"
            + (f", guest halt polling {polling} ns" if polling is not None else "")
            + ". How long an idle core polls before it halts sets the wake-up latency that the"
            " round-trip rows measure"
        )
    return lines + ["", "Commands (`bench/run.sh`):", "", "```", *run["commands"], "```"]


def core_section(run: Run) -> list[str]:
    """The core pair bench: both laws, wall and on-CPU, per D."""
    medians = run.core["medians"] if run.core else {}
    laws = [law for law in CORE_GROUPS if medians.get(law, {}).get("cpu")]
    dims = sorted({int(d) for law in laws for d in medians[law]["cpu"]})
    name = {"1": "section 1", "1b": "1b"}
    columns: list[Column] = [col("D")]
    columns += [
        (f"{name[law]} {label} ns", lambda r, a=law, c=clock: fmt(run.core_ns(a, c, r["D"])))
        for clock, label in CLOCKS.items()
        for law in laws
    ]
    lines = [
        "## Core (`cargo bench -p esa-core --bench pair`)",
        "",
        "One probe + report through `esa_core::Session` (criterion median per pair). `1b` = "
        "every CONTRACT.md section 1b field on (`normalize_response`, `shift_leak = 0.005`, "
        "`trust_region = 1`, as `EsaConfig()` sets them), an action scale with every probe, and "
        "Algorithm 1's applied action read after the probe (as the server does for every "
        "`ProbeResponse`) with Q there reported as the reference.",
        "",
        table([{"D": d} for d in dims], columns),
    ]
    extra = []
    for d in dims:
        one, other = run.core_ns("1", "cpu", d), run.core_ns("1b", "cpu", d)
        if one and other:
            extra.append(f"D = {d}: +{fmt(other - one)} ns ({other / one:.2f}x)")
    if extra:
        lines += ["", "Section 1b over section 1, on-CPU: " + "; ".join(extra) + "."]
    return lines


def server_section(run: Run) -> list[str]:
    """The Rust load generator's latency, throughput and memory."""
    server = run.server or {}
    bounds = server["bounds"]
    warmup, window = (bounds[k]["secs"] + bounds[k]["nanos"] / 1e9 for k in ("warmup", "window"))
    where = [col("socket"), col("api"), col("batch")]
    lines = [
        "## Server, from the Rust load generator (`esa-bench`)",
        "",
        f"Sessions of D = {server['dim']}; load generator on {server['client_threads']} tokio "
        "thread(s), the server with its default runtime (one worker per core). Each "
        f"measurement: {warmup:g} s warm-up, then at most {window:g} s or "
        f"{bounds['max_pairs']:,} pairs. A pair = probe + report round trips; `unary` = "
        "`Probe`+`Report` (one session), `batch` = `ProbeBatch`+`ReportBatch` calls, "
        "`stream` = both on one `StepStream`. `zenoh` = the server with `--zenoh` on its "
        "loopback listener and a Zenoh peer in the load generator: one query per call, and "
        "per StepStream message, on `esa/v1/<RpcName>` (Zenoh runs its own threads in both "
        "processes, beside the tokio threads counted here). " + TONIC_WORDS,
        "",
        "### Pair latency, one client",
        "",
        table(
            server["latency"],
            [*where, col("p50_us", "p50 us", 1), col("p90_us", "p90 us", 1)]
            + [col("p99_us", "p99 us", 1), col("mean_us", "mean us", 1), col("pairs", digits=0)]
            + run.echo_columns(),
        ),
        "",
        "### Throughput, concurrent clients",
        "",
        table(
            server["throughput"],
            [*where, col("concurrency", "clients"), STEPS, col("pairs", digits=0)]
            + [col("seconds", digits=2)],
        ),
    ]
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


def bounds_words(args: dict, what: str) -> str:
    """A Python measurement's bounds."""
    return (
        f"D = {args['dim']}; {args['warmup']:g} s warm-up, then at most {args['window']:g} s "
        f"or {args['max_pairs']:,} {what} per row."
    )


def python_section(run: Run) -> list[str]:
    """The Python client's pair latency per transport."""
    python = run.python or {}
    return [
        "## Python client (`SessionBatch`)",
        "",
        "One pair = `batch.probe(actions)` + `-|probe|^2` + `batch.report(q)`; "
        + bounds_words(python["args"], "pairs")
        + " `batch` = ProbeBatch/ReportBatch calls (`use_stream=False`, the default), "
        "`stream` = the StepStream. `uds` is `EsaClient.spawn()`, what the SB3 drop-ins use "
        'with `esa_client="spawn"`; `esa-native` = `EsaClient.in_process()` (esa-core '
        'in-process, their default). `zenoh` = `EsaClient.spawn(transport="zenoh")` '
        "(esa-server `--zenoh` on loopback): queries on `esa/v1/ProbeBatch`/`ReportBatch` "
        "(`batch` and `stream` alike: a Zenoh query is one message already). "
        + TONIC_WORDS
        + " `grpcio echo` = this client's requests sent the same way by a grpcio client to a "
        "bare grpcio server (`bench/python/echo_server.py`): the same round trips in Python's "
        "own gRPC stack, where this client's are tonic's.",
        "",
        table(
            python["rows"],
            [col("server"), col("socket"), col("api"), col("envs"), *LATENCY, STEPS]
            + [*run.echo_columns(), GRPCIO],
        ),
    ]


def section_1b_section(run: Run) -> list[str]:
    """CONTRACT.md section 1b's step from Python against section 1's pair, and pipelined."""
    section_1b = run.section_1b or {}
    rows = section_1b["rows"]
    same = ("server", "socket", "api", "envs")

    def versus(row: dict, **match: str) -> dict | None:
        return find(rows, **{k: row[k] for k in same}, **match)

    def over_pair(row: dict) -> str:
        base = versus(row, law="1", mode="pair")
        return f"{row['p50_us'] / base['p50_us']:.2f}x" if base else "-"

    lines = [
        "## CONTRACT.md section 1b from Python: the cost of the additions, and the pipelined step",
        "",
        bounds_words(section_1b["args"], "steps")
        + " `law 1, pair` = `probe` + `-|probe|^2` + `report` (as in the Python client "
        "section). `law 1b` = every section 1b field on (`EsaConfig()`'s), "
        "`pair` = `probe_applied(actions, action_scales=0.3)` + the critic at the probes and the "
        "applied actions in one batch + `report(q, q_references=...)`: two round trips; "
        "`pipelined` = the same with `report(..., defer=True)`: the report is sent with the "
        "next step's probe, one round trip per step on the StepStream (with `batch` calls it "
        "would still be two, so not measured); `step` = `SessionBatch.step` of a quadratic "
        "critic, ESAPPO's step, one engine call in-process. Time is per env step of all N envs. "
        + TONIC_WORDS,
        "",
        table(
            rows,
            [col(k) for k in (*same, "law", "mode")]
            + [*LATENCY, STEPS, ("p50 vs law 1 pair", over_pair), *run.echo_columns()],
        ),
    ]
    pipelined = [(r, versus(r, law="1b", mode="pair")) for r in rows if r["mode"] == "pipelined"]
    lines += ["", "Pipelined step against the sequential pair (both section 1b):", ""]
    return lines + [
        f"- {r['server']} {r['socket']}/{r['api']}, N = {r['envs']}: p50 {fmt(r['p50_us'])} us "
        f"against {fmt(pair['p50_us'])} us ({r['p50_us'] / pair['p50_us']:.2f}x)"
        for r, pair in pipelined
        if pair
    ]


def training_section(run: Run) -> list[str]:
    """The training-overhead ratios and where the ESA agents' time went."""
    training = run.training or {}
    args = training["args"]

    def bucket(r: dict, name: str) -> float:
        return float(np.mean([b.get(name, 0.0) for b in r["esa_buckets"]]))

    def without_round_trips(r: dict) -> str:
        esa, plain = np.mean(r["esa_seconds"]), np.mean(r["plain_seconds"])
        return f"{(esa - bucket(r, 'round_trips')) / plain:.2f}"

    def seconds(key: str) -> Callable[[dict], str]:
        return lambda r: ", ".join(fmt(s, 2) for s in r[key])

    return [
        "## Training overhead",
        "",
        f"{args['env_id']}, {args['n_envs']} env(s) (DummyVecEnv; 1 is SB3's default), seed "
        f"{args['seed']}, torch on one thread, SB3 defaults except PPO "
        f"`n_steps={args['ppo_n_steps']}` per env, `batch_size=64` and SAC "
        f"`learning_starts={args['sac_learning_starts']}` (TD3 too); ESA agents with their "
        "family's shipped default (`EsaConfig.ppo()`, `EsaConfig.off_policy()`; the gate keeps "
        "ESA off while the critic is poor, and ESAPPO's fades it out by half the budget), with "
        "the same at `gate=None` (and ESAPPO's at `fade=None`: ESA at every step once a critic "
        'exists), the placebo (`esa_control="placebo"`) and the gradient control '
        '(`esa_control="gradient"`, `[none]`: no engine), each ESA agent on every engine '
        "(`esa_client`): `[inprocess]` = esa-core in the trainer's process (None), `[sidecar]` "
        '= a private esa-server on a Unix socket (`"spawn"`) through the Rust client of '
        "`esa_client._native` (its StepStream, one pipelined round trip per step). Wall-clock "
        f"of `learn()`, {args['ppo_repeats']} repeats of PPO's pairs and {args['repeats']} of "
        f"SAC's and TD3's, family by family, after {args['warmup_runs']} short untimed run(s) "
        "of every agent; a family's plain agent and its ESA agents train side by side, one at "
        f"a time, each handing the turn to the next after {args['slice_s']} s (round-robin, "
        "reversed every other repeat), and an agent's time is the sum of its turns, so a drift "
        "of the host's speed falls on all of them alike. Ratio = median of the per-repeat "
        "ratios, with a 95 % percentile-bootstrap interval of that median in brackets (10,000 "
        "resamples of the pairs; 3 pairs or more). The verdict is the median's.",
        "",
        table(
            training["rows"],
            [
                ("pair", lambda r: f"{r['esa']} / {r['plain']}"),
                col("n_envs", "envs"),
                col("steps", digits=0),
                ("plain s", seconds("plain_seconds")),
                ("ESA s", seconds("esa_seconds")),
                ("ratio", ratio_interval),
            ]
            + [
                (f"{header} s", lambda r, n=name: fmt(bucket(r, n), 2))
                for name, header in BUCKETS.items()
            ]
            + [("ratio without round trips", without_round_trips)],
        ),
        "",
        "Split of the ESA agents' time (mean over repeats): `round trips` = inside "
        "`SessionBatch.probe_applied` (which carries the previous step's deferred report) and "
        "`.flush` (client, network, server); `ESA step` = the whole `EsaRuntime.step` (round "
        "trips, the critic at the probes and applied actions, and on one step in eight at the "
        "sampled actions for the `esa/improvement` statistic); `critic fit` = ESAPPO's "
        "advantage-head fit and gate check. `ratio without round trips` = (ESA s - round trips "
        "s) / plain s: what the agent would cost with a free service.",
    ]


# ESA's budget on RLlib's sampled env steps/s (plain's rate over ESA's): with the sessions in
# each runner, and through servers (one shared server; Zenoh shards held to the same).
RLLIB_LIMITS = {"in-runner": 1.10, "shared": 1.20, "zenoh": 1.20}
RLLIB_SETUPS = ("plain", "in-runner", "shared", "zenoh")
RLLIB_CONFIGS = (None, "default", "ungated")
HEADROOM = 0.5
"""Spare capacity the shards formula keeps: an iteration's mean rate understates the rate of
its sampling phase (PPO's runners all sample, then all wait for the learner)."""
CLUSTER_SIZES = (1, 8, 64, 1000)


def shards_needed(runners: int, rate: float, capacity: float, headroom: float = HEADROOM) -> int:
    """Servers (shards) that N runners need: ``ceil(N * r * (1 + headroom) / C)``, at least 1.

    Args:
        runners: N, the env runners of the cluster.
        rate: r, the session-steps per second one runner asks of the service.
        capacity: C, the session-steps per second one server serves at saturation.
        headroom: The share of C kept spare.
    """
    if rate < 0 or capacity <= 0 or runners < 1:
        raise ValueError(f"expected N >= 1, r >= 0 and C > 0, got {runners}, {rate}, {capacity}")
    return max(1, math.ceil(runners * rate * (1 + headroom) / capacity))


def rllib_rows(data: dict) -> list[dict]:
    """The RLlib scaling rows, one per (algo, runners, setup, ESA config), over repeats.

    ``env_steps_per_s`` and the rest are medians over the repeats; ``ratio`` is the median of
    the per-repeat ratios plain rate / this row's rate (> 1: ESA slower).
    """
    rows = data["rows"]
    keys = sorted(
        {(r["algo"], r["runners"], r["setup"], r["esa"]) for r in rows},
        key=lambda k: (k[0], k[1], RLLIB_SETUPS.index(k[2]), RLLIB_CONFIGS.index(k[3])),
    )
    out = []
    for algo, runners, setup, esa in keys:
        mine = [
            r
            for r in rows
            if (r["algo"], r["runners"], r["setup"], r["esa"]) == (algo, runners, setup, esa)
        ]

        def median(key: str, of: list[dict] = mine) -> float | None:
            values = [r[key] for r in of if r.get(key) is not None]
            return float(np.median(values)) if values else None

        ratios = []
        for r in mine:
            plain = find(rows, algo=algo, runners=runners, setup="plain", repeat=r["repeat"])
            if plain and setup != "plain":
                ratios.append(plain["env_steps_per_s"] / r["env_steps_per_s"])
        out.append(
            {
                "algo": algo,
                "runners": runners,
                "setup": setup,
                "esa": esa or "-",
                "repeats": len(mine),
                "env_steps_per_s": median("env_steps_per_s"),
                "ratio": float(np.median(ratios)) if ratios else None,
                "limit": RLLIB_LIMITS.get(setup),
                "esa_active": median("esa_active"),
                "session_steps_per_s": median("session_steps_per_s"),
                "server_requests_per_s": median("server_requests_per_s"),
                "load": median("loadavg_1m_before"),
            }
        )
    return out


def rllib_verdict(row: dict) -> str:
    """PASS or MISS of a row's ratio against its setup's budget ("-" for plain)."""
    if row["ratio"] is None or row["limit"] is None:
        return "-"
    return "PASS" if row["ratio"] <= row["limit"] else "MISS"


def capacity(run: Run, socket: str, batch: int) -> dict | None:
    """esa-bench's throughput row over ``socket`` at ``batch`` sessions per message."""
    return find(run.rows("server", "throughput"), socket=socket, api="stream", batch=batch)


def per_runner_rate(rows: list[dict], algo: str) -> tuple[float, dict] | None:
    """r: the session-steps/s one runner asks, from the shared server's 1-runner row.

    The config whose ESA acted most (ungated before default) wins; without a shared row, the
    in-runner one's.
    """
    for setup in ("shared", "in-runner"):
        candidates = [
            r
            for r in rows
            if r["algo"] == algo
            and r["runners"] == 1
            and r["setup"] == setup
            and r["session_steps_per_s"]
        ]
        if candidates:
            best = max(candidates, key=lambda r: r["esa_active"] or 0.0)
            return best["session_steps_per_s"], best
    return None


def rllib_section(run: Run) -> list[str]:
    """RLlib scaling: the rows, one server's saturation and the shards a cluster needs."""
    data = run.rllib_scaling or {}
    args, hosts = data["args"], data["host_start"]
    rows = rllib_rows(data)
    cores = hosts["cores"]
    most = max((r["runners"] for r in rows), default=0)
    lines = [
        "## RLlib scaling",
        "",
        f"`bench/python/rllib_scaling.py`: RLlib's PPO and SAC (new API stack, torch) on "
        f"{data['env']} with N env runners of one env each (`num_cpus_per_env_runner=1`, Ray "
        f"given N CPUs), the learner in the driver. Setups: `plain` = RLlib alone; `in-runner` "
        "= `with_esa`'s default, each runner keeps its sessions in its own process; `shared` = "
        "one esa-server over TCP on loopback (`EsaService(address=...)`); `zenoh` = "
        f"{data['shards']} esa-server shards over Zenoh (`EsaService(zenoh=..., shards="
        f"{data['shards']})`). ESA configs: `default` = what `with_esa` ships "
        "(`EsaConfig.ppo()`, `EsaConfig.off_policy()`, `budget=1,000,000`), whose gate keeps ESA "
        "off while the critic is poor, as it is on a run this short; `ungated` = the same with "
        "`gate=None` (PPO also `fade=None`): ESA acts on every step, its cost while it acts and "
        f"the load a server sees. A row: {args['warmup']} untimed iteration(s), then env steps "
        f"sampled (`num_env_steps_sampled_lifetime`) over the wall-clock of {args['iterations']} "
        "timed `train()` iterations (sampling and learning: what a user sees); PPO "
        f"`train_batch_size_per_learner={args['ppo_batch']}`, `num_epochs={args['ppo_epochs']}`, "
        f"minibatches of 250; SAC `min_sample_timesteps_per_iteration={args['sac_steps']}`, "
        f"learning from {args['sac_learning_starts']} steps, "
        f"`rollout_fragment_length={args.get('sac_fragment', 'auto')}`: a training step samples "
        "that many env steps per runner, then makes one gradient update (RLlib's `auto`, 1, "
        "gives a few env steps/s here, too few to time ESA's per-step work); otherwise RLlib's "
        f"defaults. `shared` and `zenoh` run the {args.get('server_configs', 'ungated')} config "
        "only: with the default's gate "
        "closed no runner opens a session, and they would time the in-runner default again. "
        "The setups of one (algo, N) run "
        f"back to back, {args['repeats']} time(s), in reverse order every other repeat; a "
        "figure is the median over repeats. `ratio` = plain's env steps/s over the row's "
        "(> 1: ESA slower), against 1.10x in the runners and 1.20x through servers (the Zenoh "
        "shards held to the server's budget). `active` = share of steps ESA acted on "
        "(`env_runners/esa/active`); `asked` = session-steps/s the runners asked of their "
        "service (env steps x active: one session per runner); `server req/s` = the shared "
        "server's `esa_requests_total` over the timed window (one fused StepStream message "
        "per session-step). A row whose ESA was not active prices only the gate's check.",
        "",
        f"Host during this part: {cores} cores, {fmt(hosts['ram_gib'])} GiB; load average "
        f"(1, 5, 15 min) {', '.join(f'{x:.2f}' for x in hosts['loadavg'])} at its start, "
        f"{', '.join(f'{x:.2f}' for x in data['host_end']['loadavg'])} at its end, "
        f"{data['wall_s'] / 60:.0f} min in all.",
    ]
    # N runners, the learner, and the server(s) each want a core.
    if most + 2 > cores:
        lines += [
            "",
            f"**CPU-bound rows.** This host has {cores} cores. A row of N runners wants N + 1 "
            "(the runners and the learner), N + 2 or more with a server: every row with "
            f"{max(cores, 1)} runners or more is oversubscribed, and so is every `shared` and "
            "`zenoh` row"
            + (f" with more than {cores - 2} runner(s)" if cores > 2 else "")
            + ". There the runners, the learner "
            "and the server(s) take turns on the same cores, so env steps/s is set by CPU, not "
            "by ESA's latency or the server's capacity, and a ratio measures how much CPU "
            "ESA's work (and a server's) takes from the runners: CPU contention, not the cost "
            "a runner with a core of its own would pay. The rows of 4 and 8 runners and the "
            "saturation check belong on a host with at least N + 2 cores (10 for 8 runners), or "
            "a cluster with the server on a node of its own; here, read the 1-runner rows, "
            "where the server's few hundred requests a second take little of a core.",
        ]
    lines += [
        "",
        table(
            rows,
            [col("algo"), col("runners"), col("setup"), col("esa", "ESA config")]
            + [col("env_steps_per_s", "env steps/s", 0)]
            + [("ratio", lambda r: "-" if r["ratio"] is None else f"{r['ratio']:.2f}x")]
            + [("target", lambda r: "-" if r["limit"] is None else f"<= {r['limit']:.2f}x")]
            + [("", rllib_verdict), col("esa_active", "active", 2)]
            + [col("session_steps_per_s", "asked session-steps/s", 0)]
            + [col("server_requests_per_s", "server req/s", 0), col("load", "load 1m", 1)],
        ),
    ]
    lines += rllib_saturation(run, rows)
    return lines


def rllib_saturation(run: Run, rows: list[dict]) -> list[str]:
    """Where one server saturates, and the shards formula worked to 1,000 runners."""
    tcp, zenoh = capacity(run, "tcp", 1), capacity(run, "zenoh", 1)
    lines = ["", "### Where one server saturates, and how many shards N runners need", ""]
    if not tcp:
        return lines + ["Not worked: the run has no esa-bench throughput rows (Server section)."]
    c_tcp = tcp["session_steps_per_s"]
    c_zenoh = zenoh["session_steps_per_s"] if zenoh else None
    lines += [
        "C = one server's capacity, from the esa-bench throughput rows of this run (Server "
        "section) at one session per message, as a runner of one env sends them: "
        f"tcp/stream batch 1 = **{fmt(c_tcp, 0)} session-steps/s** ({tcp['concurrency']} "
        "clients)"
        + (f"; one Zenoh shard, zenoh/stream batch 1 = **{fmt(c_zenoh, 0)}**" if c_zenoh else "")
        + ". Those rows count a probe + report pair (two round trips) per session-step where a "
        "runner sends one fused message, and ran with the load generator on the server's "
        "cores: C is a lower bound. A runner with more envs sends them in one message, and "
        "the batch-64 rows serve some 40x more session-steps/s. r = session-steps/s one runner "
        "asks, from the 1-runner `shared` row (its ESA config with the most active steps). "
        f"shards(N) = ceil(N x r x (1 + {HEADROOM:g}) / C), {HEADROOM:.0%} headroom since an "
        "iteration's mean rate understates its sampling phase's.",
        "",
    ]
    measured, worked, checks = [], [], []
    for algo in sorted({r["algo"] for r in rows}):
        found = per_runner_rate(rows, algo)
        if found is None:
            continue
        rate, base = found
        for r in rows:
            if r["algo"] != algo or r["setup"] != "shared" or r["esa"] != base["esa"]:
                continue
            demand = r["runners"] * rate
            served = r["session_steps_per_s"] or 0.0
            measured.append(
                {
                    "algo": algo,
                    "runners": r["runners"],
                    "ESA config": r["esa"],
                    "asked": demand,
                    "served": served,
                    "served / asked": f"{served / demand:.2f}",
                    "of C": f"{served / c_tcp:.1%}",
                    "shards(N)": shards_needed(r["runners"], rate, c_tcp),
                    "ratio": "-" if r["ratio"] is None else f"{r['ratio']:.2f}x",
                }
            )
        for n in CLUSTER_SIZES:
            worked.append(
                {
                    "algo": algo,
                    "N": f"{n:,}",
                    "r": rate,
                    "N x r": n * rate,
                    "tcp servers": shards_needed(n, rate, c_tcp),
                    "zenoh shards": shards_needed(n, rate, c_zenoh) if c_zenoh else "-",
                }
            )
        saturates = c_tcp / (rate * (1 + HEADROOM))
        checks.append(
            f"{algo}: r = {fmt(rate, 0)} session-steps/s per runner ({base['esa']}, "
            f"active {base['esa_active'] or 0:.2f}), so one TCP server holds "
            f"{math.floor(saturates):,} runners with the headroom "
            f"({math.floor(c_tcp / rate):,} at saturation)"
            + (
                f", one Zenoh shard {math.floor(c_zenoh / (rate * (1 + HEADROOM))):,}"
                if c_zenoh
                else ""
            )
            + "."
        )
    if not measured:
        return lines + ["Not worked: the run has no `shared` rows with ESA active."]
    lines += [
        "Measured: the shared server's rows. `asked` = N x r, what N runners at the 1-runner "
        "rate would ask; `served` = what the server served (the row's asked session-steps/s); "
        "`of C` = served over C.",
        "",
        table(
            measured,
            [col("algo"), col("runners"), col("ESA config"), col("asked", digits=0)]
            + [col("served", digits=0), col("served / asked"), col("of C")]
            + [col("shards(N)"), col("ratio")],
        ),
        "",
        "The formula worked from these r and C:",
        "",
        table(
            worked,
            [col("algo"), col("N"), col("r", digits=0), col("N x r", digits=0)]
            + [col("tcp servers"), col("zenoh shards")],
        ),
        "",
        *[f"- {line}" for line in checks],
        "- Check against the measured rows: where shards(N) is 1, one server should serve what "
        "the runners ask (served / asked near 1) and the `shared` ratio should stay within "
        "1.20x. served / asked falling below 1 with `of C` far under 100 % is the runners "
        "slowing (on this host, CPU contention: fewer env steps, so fewer session-steps asked), "
        "not the server saturating; a server at saturation serves near C however many runners "
        "ask.",
    ]
    return lines


@dataclass
class Args:
    """Writes BENCHMARKS.md and the latency plot from the results of one bench run."""

    results: Path = REPO_ROOT / "bench/results"
    """Folder of the run's JSON results (the plot goes there too)."""
    out: Path = REPO_ROOT / "BENCHMARKS.md"
    """The page to write."""
    snapshot_core: Path | None = None
    """Only write the core bench's medians from ``target/criterion`` to this JSON file."""


def main(args: Args) -> None:
    """Reads the results and writes BENCHMARKS.md and the PNG."""
    if args.snapshot_core:
        medians = criterion_medians(REPO_ROOT / "target/criterion")
        args.snapshot_core.write_text(
            json.dumps({"unit": "ns per pair (criterion median)", "medians": medians}, indent=2)
        )
        return
    parts = ("run", "core", "server", "python", "section_1b", "training", "sizes", "rllib_scaling")
    run = Run(*(load(args.results / f"{part}.json") for part in parts))
    plot(run, args.results / PLOT)
    lines = [
        "# Benchmarks",
        "",
        "`make bench` (`bench/run.sh`), written by `bench/report.py` from its results "
        "in `bench/results/`; do not edit by hand. The performance targets first, then every "
        "measurement.",
        "",
        *provenance_lines(run),
        "",
        "## Targets",
        "",
        table(targets(run), [col(k) for k in ("target", "goal", "measured", "")]),
        "",
        "A training ratio is the median over repeated pairs, with a 95 % bootstrap interval "
        "of that median in brackets; the verdict is the median's (Training overhead, below).",
        "",
        f"![pair latency vs batch size](bench/results/{PLOT})",
    ]
    sections = [
        (run.run, machine_section),
        (run.core, core_section),
        (run.server, server_section),
        (run.python, python_section),
        (run.training, training_section),
        (run.section_1b, section_1b_section),
        (run.rllib_scaling, rllib_section),
    ]
    for data, section in sections:
        if data:
            lines += ["", *section(run)]
    args.out.write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out} and {args.results / PLOT}")


if __name__ == "__main__":
    main(tyro.cli(Args))
