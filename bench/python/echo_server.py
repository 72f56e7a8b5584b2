"""The floor the Python client's gRPC rows stand beside: a bare grpcio echo server.

It answers ``/esa.bench.Echo/Echo`` with the bytes it was sent, and each message on
``/esa.bench.Echo/Stream`` likewise (no messages decoded, no sessions), in a process of its
own as esa-server runs in its own. ``client_latency.py``
times a grpcio client's pair of such calls, sized like each row's requests, on the same
kind of socket.

Usage::

    python bench/python/echo_server.py [--listen 127.0.0.1:0 | --listen unix:/path]

Prints ``listening on ADDR`` once it accepts calls; stops on SIGINT/SIGTERM.
"""

from __future__ import annotations

import signal
import threading
from concurrent import futures
from dataclasses import dataclass

import grpc
import tyro

SERVICE = "esa.bench.Echo"


@dataclass
class Args:
    """A grpcio echo server."""

    listen: str = "127.0.0.1:0"
    """``host:port`` (port 0: a free one) or ``unix:/path``."""


def main() -> None:
    """Serves until SIGINT or SIGTERM."""
    args = tyro.cli(Args)
    server = grpc.server(futures.ThreadPoolExecutor(max_workers=4))
    handlers = {
        "Echo": grpc.unary_unary_rpc_method_handler(lambda request, context: request),
        "Stream": grpc.stream_stream_rpc_method_handler(lambda requests, context: requests),
    }
    server.add_generic_rpc_handlers((grpc.method_handlers_generic_handler(SERVICE, handlers),))
    port = server.add_insecure_port(args.listen)
    server.start()
    host = args.listen.rpartition(":")[0]
    address = args.listen if args.listen.startswith("unix:") else f"{host}:{port}"
    print(f"listening on {address}", flush=True)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    stop.wait()
    server.stop(grace=None)


if __name__ == "__main__":
    main()
