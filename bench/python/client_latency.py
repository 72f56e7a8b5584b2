"""SessionBatch pair latency from Python, per transport, beside a bare grpcio echo.

One pair is what a trainer does per VecEnv step: ``batch.probe(actions, starts)``,
the critic at the probes (here ``-|probe|^2``), ``batch.report(q)``. Measured for
N = 1, 8, 64 envs of D = 6 against:

- esa-server over loopback TCP and a Unix socket, each with ``ProbeBatch``/``ReportBatch``
  calls and with the ``StepStream``, through the client's gRPC transport;
- esa-server with ``--zenoh`` on loopback (``EsaClient.spawn(transport="zenoh")``): the same two
  ways, as queries on ``esa/v1/ProbeBatch``/``ReportBatch`` or one query per
  StepStream message on ``esa/v1/StepStream``;
- ``EsaClient.in_process()``: esa-core in this process (``esa_client._native``), the
  in-process engine of the SB3 drop-ins.

Beside each row of the table on TCP or a Unix socket: a grpcio client's pair of echoes (two
calls, or two messages on one stream for ``stream``) to a bare grpcio echo server
(``echo_server.py``, its own process) on the same kind of socket, each the size of the row's
requests (``grpcio_echo_p50_us``): the same round trips in Python's own gRPC stack. The
client's gRPC is tonic, so its floor is tonic's echo, which esa-bench measures.

Section 1b of CONTRACT.md (``--parts 1b``, written to ``--section-1b-out``): the
SessionBatch step at N = ``--section-1b-envs`` with every section 1b field on
against section 1's, on esa-server (TCP and Unix socket, batch calls and the
StepStream) and in-process. Each step of the section 1b rows sends the policy's
standard deviation (``action_scales``) and reports ``q_references``, the critic at
the applied actions, scored in the same critic batch as the probes. Two ways:

- ``pair``: ``probe_applied`` + the critic + ``report``: two round trips per step;
- ``pipelined``: ``probe_applied`` + the critic + ``report(defer=True)``: the
  report rides with the next step's probe, one round trip per step on the
  StepStream (two messages written before either answer is read);
- ``step`` (in-process only): ``SessionBatch.step`` of a quadratic critic, ESAPPO's step,
  which the engine runs in one call.

Usage::

    python bench/python/client_latency.py [--window 2.0] [--out bench/results/python.json]
    python bench/python/client_latency.py --parts 1b   # only the section 1b rows
"""

from __future__ import annotations

import dataclasses
import json
import queue
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass
from pathlib import Path

import grpc
import numpy as np
import tyro
from esa_client import EsaClient, QuadraticCritic, SessionBatch, SessionConfig
from esa_client._proto.esa.v1 import esa_pb2

from echo_server import SERVICE
from servers import echo_server, esa_server_tcp, server_binary

# Steps per episode, as in the MuJoCo tasks (the episode start rides on a probe).
EPISODE_STEPS = 1000


@dataclass
class Args:
    """SessionBatch pair latency from Python, per transport."""

    envs: str = "1,8,64"
    """Batch sizes N (envs) of the main table, comma-separated."""
    dim: int = 6
    """Action dimension D."""
    warmup: float = 0.3
    """Seconds of untimed pairs before each measurement."""
    window: float = 2.0
    """Seconds of timed pairs per measurement (at most ``max_pairs``)."""
    max_pairs: int = 20_000
    """Timed pairs per measurement at most."""
    out: str = "bench/results/python.json"
    """JSON of the main table."""
    parts: str = "main,1b"
    """Which measurements: "main" (the table of every transport) and/or "1b"."""
    section_1b_envs: str = "8"
    """Batch sizes N of the section 1b rows, comma-separated."""
    section_1b_out: str = "bench/results/section_1b.json"
    """JSON of the section 1b rows."""


def session_config(dim: int) -> SessionConfig:
    """The same per-session config as the Rust load generator sends."""
    return SessionConfig(
        action_dim=dim,
        dt=0.01,
        amplitude=0.2,
        frequency=[40.0 + 5.0 * i for i in range(dim)],
        learning_rate=0.05,
        action_low=-1.0,
        action_high=1.0,
    )


def section_1b_config(dim: int) -> SessionConfig:
    """``session_config`` with every section 1b field on, as ``EsaConfig()`` sets them."""
    return dataclasses.replace(
        session_config(dim), normalize_response=True, shift_leak=0.005, trust_region=1.0
    )


def section_1_step(batch, actions: np.ndarray) -> Callable[[], None]:
    """Section 1's pair: probe, the critic at the probes, report."""

    def step() -> None:
        probes = batch.probe(actions)
        batch.report(-np.sum(probes**2, axis=1))

    return step


def section_1b_step(batch, actions: np.ndarray, *, defer: bool) -> Callable[[], None]:
    """Algorithm 1's step with the section 1b inputs; ``defer`` pipelines the report."""
    scales = np.full(actions.shape, 0.3)

    def step() -> None:
        probes, applied = batch.probe_applied(actions, action_scales=scales)
        # One critic batch scores the probes and the applied actions (the references).
        q = -np.sum(np.concatenate([probes, applied]) ** 2, axis=1)
        batch.report(q[: batch.n], q_references=q[batch.n :], defer=defer)

    return step


def closed_form_step(batch, actions: np.ndarray) -> Callable[[], None]:
    """ESAPPO's step: ``SessionBatch.step`` of a quadratic critic, evaluated by the engine."""
    rng = np.random.default_rng(1)
    n, dim = actions.shape
    critic = QuadraticCritic(
        rng.normal(size=(n, dim)),
        -np.abs(rng.normal(size=(n, dim))),
        rng.normal(size=n),
        np.full(dim, -1.0),
        np.full(dim, 1.0),
    )
    scales = np.full(actions.shape, 0.3)

    def step() -> None:
        batch.step(actions, critic, action_scales=scales, paired=True)

    return step


def measure(batch, args: Args, law: str = "1", mode: str = "pair") -> dict:
    """Runs steps on ``batch`` for the warm-up, then times each step; returns the summary.

    ``law`` "1" is section 1's pair; "1b" is Algorithm 1's step with the section 1b
    inputs, ``mode`` "pair" (two round trips), "pipelined" (deferred report) or "step"
    (``SessionBatch.step`` of a quadratic critic, ESAPPO's).
    """
    rng = np.random.default_rng(0)
    actions = rng.uniform(-0.5, 0.5, size=(batch.n, batch.action_dim))
    if law == "1":
        one_step = section_1_step(batch, actions)
    elif mode == "step":
        one_step = closed_form_step(batch, actions)
    else:
        one_step = section_1b_step(batch, actions, defer=mode == "pipelined")

    def pair(step: int) -> None:
        if step % EPISODE_STEPS == 0:
            batch.reset()
        one_step()

    result = timed(pair, batch.n, args)
    batch.flush()
    return result


def timed(pair: Callable[[int], None], n: int, args: Args) -> dict:
    """Runs ``pair(step)`` for the warm-up, then times each pair of the window."""
    step = 0
    end = time.perf_counter() + args.warmup
    while time.perf_counter() < end:
        pair(step)
        step += 1
    times = []
    end = time.perf_counter() + args.window
    while len(times) < args.max_pairs and time.perf_counter() < end:
        start = time.perf_counter_ns()
        pair(step)
        times.append(time.perf_counter_ns() - start)
        step += 1
    us = np.asarray(times) / 1e3
    return {
        "pairs": len(times),
        "p50_us": float(np.percentile(us, 50)),
        "p90_us": float(np.percentile(us, 90)),
        "p99_us": float(np.percentile(us, 99)),
        "mean_us": float(us.mean()),
        "session_steps_per_s": float(n / (us.mean() / 1e6)),
    }


def request_sizes(batch: SessionBatch) -> tuple[int, int]:
    """The encoded sizes of ``batch``'s ProbeBatch and ReportBatch requests."""
    n, steps = batch.n, [1] * batch.n
    probe = esa_pb2.ProbeBatchRequest(
        session_ids=batch.ids, steps=steps, actions=[0.1] * (n * batch.action_dim)
    )
    report = esa_pb2.ReportBatchRequest(session_ids=batch.ids, steps=steps, q_values=[0.1] * n)
    return probe.ByteSize(), report.ByteSize()


def echo_p50(address: str, sizes: tuple[int, int], stream: bool, args: Args) -> float:
    """p50 of a grpcio client's pair of echoes of ``sizes`` bytes: calls, or stream messages."""
    payloads = [b"*" * size for size in sizes]
    outbox: queue.SimpleQueue[bytes | None] = queue.SimpleQueue()
    with grpc.insecure_channel(address) as channel:
        call = channel.unary_unary(f"/{SERVICE}/Echo")
        answers = channel.stream_stream(f"/{SERVICE}/Stream")(iter(outbox.get, None))

        def pair(_: int) -> None:
            for payload in payloads:
                if stream:
                    outbox.put(payload)
                    next(answers)
                else:
                    call(payload)

        p50 = timed(pair, 1, args)["p50_us"]
        outbox.put(None)  # ends the stream
        return float(p50)


@contextmanager
def echo_servers() -> Iterator[dict[str, str]]:
    """The grpcio echo on loopback TCP and on a Unix socket: their addresses by socket kind."""
    with (
        tempfile.TemporaryDirectory() as tmp,
        echo_server("127.0.0.1:0") as tcp,
        echo_server(f"unix:{tmp}/echo.sock") as uds,
    ):
        yield {"tcp": tcp, "uds": uds}


def echo_text(row: dict) -> str:
    """A row's echo p50 for the progress lines."""
    echo = row["grpcio_echo_p50_us"]
    return "n/a" if echo is None else f"{echo:.1f} us"


def with_echo(row: dict, batch: SessionBatch, echoes: dict[str, str], args: Args) -> dict:
    """``row`` with the grpcio echo of its socket kind (None in-process and over Zenoh)."""
    address = echoes.get(row["socket"])
    stream = row["api"] == "stream"
    echo = address and echo_p50(address, request_sizes(batch), stream, args)
    return {**row, "grpcio_echo_p50_us": echo}


@contextmanager
def client_at(address: AbstractContextManager[str]) -> Iterator[EsaClient]:
    """An ``EsaClient`` (gRPC, the Rust client) on the address a server context yields."""
    with address as target, EsaClient.connect(target, timeout=30.0) as client:
        yield client


Target = tuple[str, str, str, Callable[[], AbstractContextManager]]
"""(server, socket, api, a factory of a context yielding a client)."""


def targets() -> list[Target]:
    """Every (server, socket, api) combination this benchmark measures."""
    out: list[Target] = []
    for api in ("batch", "stream"):
        out.append(("esa-server", "tcp", api, lambda: client_at(esa_server_tcp())))
        out.append(
            ("esa-server", "uds", api, lambda: EsaClient.spawn(server_binary(), timeout=30.0))
        )
        out.append(
            (
                "esa-server",
                "zenoh",
                api,
                lambda: EsaClient.spawn(server_binary(), transport="zenoh", timeout=30.0),
            )
        )
    out.append(("esa-native", "in-process", "-", EsaClient.in_process))
    return out


def section_1b_targets() -> list[Target]:
    """The transports of the section 1b rows: every target but Zenoh (TCP, Unix socket, in-process).

    ``batch``: unary calls; ``stream``: the StepStream.
    """
    return [target for target in targets() if target[1] != "zenoh"]


# (law, mode) of each section 1b row; pipelining only changes anything on the StepStream.
SECTION_1B_ROWS = [("1", "pair"), ("1b", "pair"), ("1b", "pipelined"), ("1b", "step")]


def main_rows(args: Args) -> list[dict]:
    """Section 1's pair on every target for every N."""
    envs = [int(n) for n in args.envs.split(",")]
    rows = []
    with echo_servers() as echoes:
        for server, socket, api, connect in targets():
            with connect() as client:
                for n in envs:
                    batch = client.create_batch(
                        session_config(args.dim), n, use_stream=api == "stream"
                    )
                    result = measure(batch, args)
                    row = {"server": server, "socket": socket, "api": api, "envs": n, **result}
                    row = with_echo(row, batch, echoes, args)
                    rows.append(row)
                    batch.close()
                    print(
                        f"{server:<14} {socket:<10} {api:<6} N={n:<3} p50 {row['p50_us']:8.1f} us"
                        f"  p99 {row['p99_us']:8.1f} us  grpcio echo p50 {echo_text(row)}",
                        flush=True,
                    )
    return rows


def section_1b_rows(args: Args) -> list[dict]:
    """Section 1's pair against section 1b's pair and pipelined step, same process and time."""
    envs = [int(n) for n in args.section_1b_envs.split(",")]
    rows = []
    for server, socket, api, connect in section_1b_targets():
        with connect() as client:
            rows += section_1b_rows_of(client, server, socket, api, envs, args)
    return rows


def section_1b_rows_of(
    client: EsaClient,
    server: str,
    socket: str,
    api: str,
    envs: list[int],
    args: Args,
) -> list[dict]:
    """The section 1b rows of one target."""
    rows = []
    for n in envs:
        for law, mode in SECTION_1B_ROWS:
            if mode == "pipelined" and api == "batch":
                continue  # two unary round trips: the same as the pair
            if mode == "step" and server != "esa-native":
                continue  # one engine call only in-process; a wire's is the pipelined
            config = session_config(args.dim) if law == "1" else section_1b_config(args.dim)
            batch = client.create_batch(config, n, use_stream=api == "stream")
            result = measure(batch, args, law, mode)
            row = {
                "server": server,
                "socket": socket,
                "api": api,
                "envs": n,
                "law": law,
                "mode": mode,
                **result,
            }
            rows.append(row)
            batch.close()
            print(
                f"{server:<14} {socket:<10} {api:<6} N={n:<3} law {law:<2} {mode:<9} "
                f"p50 {row['p50_us']:8.1f} us  p99 {row['p99_us']:8.1f} us",
                flush=True,
            )
    return rows


def write(path: str, args: Args, rows: list[dict]) -> None:
    """Writes the arguments and rows as JSON to ``path``."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"args": dataclasses.asdict(args), "rows": rows}, indent=2))
    print(f"wrote {out}")


def main() -> None:
    """Measures the requested parts and writes their JSON results."""
    args = tyro.cli(Args)
    parts = set(args.parts.split(","))
    unknown = parts - {"main", "1b"}
    if unknown:
        raise SystemExit(f"--parts: expected main and/or 1b, got {sorted(unknown)}")
    if "main" in parts:
        write(args.out, args, main_rows(args))
    if "1b" in parts:
        write(args.section_1b_out, args, section_1b_rows(args))


if __name__ == "__main__":
    main()
