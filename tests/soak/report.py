"""``tests/soak/RESULTS.md`` from one soak run's ``tests/soak/results/soak.json`` (``esa-soak``).

Usage::

    python tests/soak/report.py [--results tests/soak/results/soak.json] \
        [--out tests/soak/RESULTS.md]
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import tyro

HERE = Path(__file__).resolve().parent
# Rows of the server-state table: the peaks of each window of this many seconds.
TABLE_EVERY_S = 10.0


def _table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return "\n".join(lines + ["| " + " | ".join(row) + " |" for row in rows])


def _latency(soak: dict, phase: str) -> str:
    row = soak["latency"].get(phase)
    if row is None:
        return "n/a"
    return f"{row['p50_us']:,.0f} / {row['p99_us']:,.0f} us ({row['pairs']:,} pairs)"


def _seconds(duration: dict) -> float:
    """A Rust ``Duration`` as serde writes it, in seconds."""
    return duration["secs"] + duration["nanos"] / 1e9


def _codes(counts: dict[str, int]) -> str:
    return ", ".join(f"{n} {code}" for code, n in sorted(counts.items())) or "none"


def soak_page(soak: dict) -> list[str]:
    """The markdown lines of the soak page for one ``esa-soak`` result."""
    plan, machine, samples, floods = (
        soak["plan"],
        soak["machine"],
        soak["samples"],
        soak["floods"],
    )
    seconds = soak["seconds"]
    rss = [s["rss_mib"] for s in samples if s["rss_mib"] > 0]
    clients = soak["clients"]
    quiet_before = [
        s["rss_mib"] for s in samples if s["phase"] == "quiet" and s["t_s"] > 1.0
    ]
    summary = [
        [
            "run",
            (
                f"{seconds:.0f} s; {plan['load_clients']} load clients x {plan['batch']} sessions "
                f"(D = {plan['dim']}; even clients ProbeBatch/ReportBatch, odd ones StepStream)"
            ),
        ],
        [
            "calls served",
            (
                f"{soak['calls_served']:,} ({soak['calls_served'] / seconds:,.0f}/s), "
                f"{soak['pairs']:,} probe + report pairs"
            ),
        ],
        ["pair p50 / p99, quiet", _latency(soak, "quiet")],
        ["pair p50 / p99, during floods", _latency(soak, "flood")],
        ["pair p50 / p99, just after the restart", _latency(soak, "restart")],
        [
            "server RSS: first quiet sample / peak / last",
            f"{quiet_before[0]:.0f} / {max(rss):.0f} / {rss[-1]:.0f} MiB"
            if quiet_before and rss
            else "n/a",
        ],
        [
            "peak RSS per flood cycle",
            ", ".join(f"{f['peak_rss_mib']:.0f}" for f in floods) + " MiB",
        ],
        [
            f"connections held at most (open-files limit {plan['open_files']:,})",
            f"{soak['max_connections_open']:,} connections, {soak['max_open_files']:,} descriptors",
        ],
        [
            "connections evicted / refused",
            f"{soak['connections_evicted']:,} / {soak['connections_refused']:,}",
        ],
        [
            "flood per cycle",
            f"{floods[0]['silent_opened']:,} silent TCP connections, "
            f"{floods[0]['idle_h2_opened']:,} idle HTTP/2 connections, "
            f"{plan['stalled_streams']} StepStreams announcing 20 MB and sending 5 MB, "
            "D = 4096 sessions until refused"
            if floods
            else "none",
        ],
        [
            "stalled messages ended with",
            "; ".join(_codes(f["stalled_ended"]) for f in floods),
        ],
        [
            "D = 4096 sessions per cycle until refused",
            ", ".join(
                f"{f['big_sessions_created']:,} ({f['big_sessions_refused_with']})"
                for f in floods
            ),
        ],
        ["restart (SIGKILL) to serving again", f"{soak['restart_downtime_s']:.2f} s"],
        [
            "sessions recovered (NOT_FOUND, recreated)",
            f"{soak['sessions_recovered']:,} (after the restart and one TTL expiry)",
        ],
        [
            "lost clients",
            (
                f"{soak['lost_clients']} (longest gap between two served pairs: "
                f"{max(c['longest_gap_s'] for c in clients):.2f} s)"
            ),
        ],
    ]
    buckets: dict[int, list[dict]] = {}
    for sample in samples:
        buckets.setdefault(int(sample["t_s"] // TABLE_EVERY_S), []).append(sample)
    rows = [
        [
            f"{index * TABLE_EVERY_S:.0f}-{(index + 1) * TABLE_EVERY_S:.0f}",
            ", ".join(dict.fromkeys(s["phase"] for s in bucket)),
            f"{max(s['rss_mib'] for s in bucket):.0f}",
            f"{max(s['open_files'] for s in bucket):,}",
            f"{max(s['connections_open'] for s in bucket):,}",
            f"{bucket[-1]['sessions_live']:,}",
            f"{max(s['session_memory_mib'] for s in bucket):.1f}",
        ]
        for index, bucket in sorted(buckets.items())
    ]
    return [
        "# Soak",
        "",
        (
            "Generated by `tests/soak/report.py` from one `make soak` run (`tests/soak/run.sh`, the "
            "`esa-soak` program): minutes of steady load on a real server started as a user "
            f"would, with an open-files limit of {plan['open_files']:,} it cannot raise, "
            f"`--session-ttl {_seconds(plan['session_ttl']):g}`, `--max-session-memory 256MiB` and "
            "`--request-timeout 5`, while flood cycles come and go, one client pauses past the "
            "TTL, and the server is killed (SIGKILL) and restarted on its port. A client whose "
            "sessions are gone recreates them under the same ids at a new episode, as "
            "`EsaClient.restore_sessions` does. Everything on loopback."
        ),
        "",
        (
            f"Machine: {machine['cores']} cores, shared: load average {machine['loadavg_start']} "
            f"at the start, {machine['loadavg_end']} at the end; steal "
            f"{machine['steal_percent']:.1f} %. Latencies include the load generator's own share "
            "of the same cores."
        ),
        "",
        _table(["figure", "measured"], summary),
        "",
        (
            f"Server state per {TABLE_EVERY_S:.0f} s window, sampled every "
            f"{_seconds(plan['sample_every']):g} s (peaks; sessions: the last sample):"
        ),
        "",
        _table(
            [
                "t (s)",
                "phase",
                "peak RSS (MiB)",
                "descriptors",
                "connections",
                "sessions",
                "session memory (MiB)",
            ],
            rows,
        ),
        *_fuzz_lines(soak.get("fuzz")),
    ]


def _fuzz_lines(fuzz: dict | None) -> list[str]:
    """The fuzz run's paragraph (``server/tests/fuzz.rs``), when ``run.sh`` ran it."""
    if not fuzz:
        return []
    return [
        "",
        (
            f"Fuzz (`server/tests/fuzz.rs`, `ESA_FUZZ_CASES={fuzz['cases']}`): "
            f"{fuzz['cases']:,} inputs per property, {fuzz['properties']} properties (arbitrary "
            "bytes; valid but extreme messages, cut or bit-flipped) through the codec and the "
            "handler for every RPC: no panic, no allocation beyond 1 MiB + 64 x the request, "
            f"state unchanged on every rejection: **{fuzz['result']}** in {fuzz['seconds']:.0f} s."
        ),
    ]


@dataclass
class Args:
    """Writes the soak page of one ``make soak`` run."""

    results: Path = HERE / "results/soak.json"
    """The soak run's JSON."""
    out: Path = HERE / "RESULTS.md"
    """The page to write."""


def main(args: Args) -> None:
    """Writes the page of ``--results`` to ``--out``."""
    page = soak_page(json.loads(args.results.read_text()))
    args.out.write_text("\n".join(page) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main(tyro.cli(Args))
