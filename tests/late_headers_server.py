"""A grpcio server whose StepStream answers its headers only with the first answer.

grpcio sends a stream's response headers with its first message when the handler is a
generator; a client that waits for the headers before it sends a request never gets one.
It serves just what ``test_client_tcp.py`` needs: ``CreateSession``, ``CloseSession`` and a
StepStream that answers each episode-start ``ProbeBatch`` as the law does at t = 0 (the
probe and the applied action are the sampled action: no shift yet, and ``sin(0) = 0``).

Usage::

    python tests/late_headers_server.py

Prints ``listening on HOST:PORT`` once it accepts calls; stops on SIGTERM.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from concurrent import futures

import grpc
from esa_client._proto.esa.v1 import esa_pb2 as pb


def step_stream(requests: Iterator[pb.StepStreamRequest], _: object) -> Iterator:
    """Answers each episode-start ProbeBatch at t = 0."""
    for request in requests:
        probe = request.probe_batch
        n = len(probe.session_ids)
        answer = pb.ProbeBatchResponse(
            probes=probe.actions,
            actions=probe.actions,
            episodes_completed=[0] * n,
            response_mean_squares=[0.0] * n,
        )
        yield pb.StepStreamResponse(probe_batch=answer)


def unary(request_type: type, answer: object) -> grpc.RpcMethodHandler:
    """A unary handler that decodes ``request_type`` and answers ``answer(request)``."""
    return grpc.unary_unary_rpc_method_handler(
        answer,
        request_deserializer=request_type.FromString,
        response_serializer=lambda message: message.SerializeToString(),
    )


def main() -> None:
    """Serves on a free loopback port until SIGTERM."""
    handlers = {
        "CreateSession": unary(
            pb.CreateSessionRequest,
            lambda request, _: pb.CreateSessionResponse(session_id=request.session_id),
        ),
        "CloseSession": unary(
            pb.CloseSessionRequest, lambda *_: pb.CloseSessionResponse()
        ),
        "StepStream": grpc.stream_stream_rpc_method_handler(
            step_stream,
            request_deserializer=pb.StepStreamRequest.FromString,
            response_serializer=lambda message: message.SerializeToString(),
        ),
    }
    server = grpc.server(futures.ThreadPoolExecutor(max_workers=4))
    server.add_generic_rpc_handlers(
        (grpc.method_handlers_generic_handler("esa.v1.EsaService", handlers),)
    )
    port = server.add_insecure_port("127.0.0.1:0")
    server.start()
    print(f"listening on 127.0.0.1:{port}", flush=True)
    stopped = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stopped.set())
    stopped.wait()
    server.stop(grace=None)


if __name__ == "__main__":
    main()
