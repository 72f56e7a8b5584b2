"""Smoke test of the esa-server image from the host (`make container-check`).

Starts the image built by deploy/container/build.sh and, from the host, checks that

1. the gRPC health service answers SERVING for the server as a whole (service "");
2. a CreateSession / Probe / Report / CloseSession round trip works over TCP;
3. the metrics port serves the Prometheus exposition with that traffic counted;
4. the process runs as the image's non-root user (uid 65532).

``--mode podman`` (the default) runs the image with ``podman run``, ports published on
loopback. ``--mode chroot`` is for machines whose sandbox refuses to start containers (crun
fails with ``setrlimit ... Operation not permitted`` inside some sandboxes): it exports the
image's filesystem with podman and runs its entrypoint under ``chroot --userspec=65532:65532``,
which proves the image holds everything the binary needs (no library from the host) but not
the container runtime itself.

Usage: python deploy/container/smoke_test.py [--image IMAGE] [--mode podman|chroot]
"""

from __future__ import annotations

import argparse
import shutil
import socket
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path

import grpc
from esa_client._proto.esa.v1 import esa_pb2
from grpc_health.v1 import health_pb2, health_pb2_grpc

UID = 65532


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def wait_serving(address: str, deadline_s: float = 30.0) -> str:
    """The health status of service "", polled until it answers or the deadline passes."""
    end = time.monotonic() + deadline_s
    with grpc.insecure_channel(address) as channel:
        health = health_pb2_grpc.HealthStub(channel)
        while True:
            try:
                reply = health.Check(
                    health_pb2.HealthCheckRequest(service=""), timeout=2
                )
                return str(
                    health_pb2.HealthCheckResponse.ServingStatus.Name(reply.status)
                )
            except grpc.RpcError:
                if time.monotonic() > end:
                    raise
                time.sleep(0.2)


def unary(channel: grpc.Channel, method: str) -> grpc.UnaryUnaryMultiCallable:
    """EsaService's ``method`` on ``channel`` (esa_client ships no grpcio service module)."""
    output = (
        esa_pb2.DESCRIPTOR.services_by_name["EsaService"]
        .methods_by_name[method]
        .output_type
    )
    return channel.unary_unary(
        f"/esa.v1.EsaService/{method}",
        request_serializer=lambda request: request.SerializeToString(),
        response_deserializer=getattr(esa_pb2, output.name).FromString,
    )


def round_trip(address: str) -> list[float]:
    """CreateSession, Probe, Report, CloseSession; returns the reported action."""
    with grpc.insecure_channel(address) as channel:
        config = esa_pb2.SessionConfig(
            action_dim=2,
            dt=0.04,
            amplitude=[0.2],
            frequency=[31.4, 15.7],
            learning_rate=[0.3],
        )
        session = unary(channel, "CreateSession")(
            esa_pb2.CreateSessionRequest(config=config), timeout=5
        )
        sid = session.session_id
        probe = unary(channel, "Probe")(
            esa_pb2.ProbeRequest(session_id=sid, step=0, action=[0.1, -0.1])
        )
        assert len(probe.probe) == 2, probe
        report = unary(channel, "Report")(
            esa_pb2.ReportRequest(session_id=sid, step=0, q_value=1.5)
        )
        assert len(report.action) == 2, report
        unary(channel, "CloseSession")(esa_pb2.CloseSessionRequest(session_id=sid))
        return list(report.action)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--image", default="localhost/esa-server:0.1.0")
    parser.add_argument("--mode", choices=("podman", "chroot"), default="podman")
    args = parser.parse_args()
    grpc_port, metrics_port = free_port(), free_port()
    tmp = Path(tempfile.mkdtemp(prefix="esa-container-"))
    name = f"esa-smoke-{grpc_port}"
    process: subprocess.Popen[bytes] | None = None
    try:
        if args.mode == "podman":
            subprocess.run(
                ["podman", "run", "-d", "--rm", "--name", name,
                 "-p", f"127.0.0.1:{grpc_port}:50051", "-p", f"127.0.0.1:{metrics_port}:9464",
                 args.image],
                check=True,
            )  # fmt: skip
        else:
            container = subprocess.run(
                ["podman", "create", args.image],
                check=True,
                capture_output=True,
                text=True,
            ).stdout.strip()
            rootfs = tmp / "rootfs"
            rootfs.mkdir()
            export = subprocess.Popen(
                ["podman", "export", container], stdout=subprocess.PIPE
            )
            subprocess.run(
                ["tar", "-x", "-C", str(rootfs)], stdin=export.stdout, check=True
            )
            export.wait()
            subprocess.run(["podman", "rm", container], check=True, capture_output=True)
            files = sorted(
                str(p.relative_to(rootfs)) for p in rootfs.rglob("*") if p.is_file()
            )
            print("image files:", ", ".join(files))
            process = subprocess.Popen(
                ["/usr/sbin/chroot", f"--userspec={UID}:{UID}", str(rootfs), "/usr/local/bin/esa-server",
                 "--listen", f"127.0.0.1:{grpc_port}",
                 "--metrics-listen", f"127.0.0.1:{metrics_port}"],
                env={},
            )  # fmt: skip
        address = f"127.0.0.1:{grpc_port}"
        status = wait_serving(address)
        assert status == "SERVING", status
        print("health:", status)
        print("round trip: Report action", round_trip(address))
        url = f"http://127.0.0.1:{metrics_port}/metrics"
        metrics = urllib.request.urlopen(url, timeout=5).read().decode()
        assert 'esa_requests_total{rpc="Probe",code="OK"} 1' in metrics, metrics
        for name in ("esa_build_info{version=", "process_resident_memory_bytes "):
            assert name in metrics, f"no {name} in {metrics}"
        print(
            "metrics: esa_requests_total counted the Probe; build info and process metrics"
        )
        if process is not None:
            uid = (
                Path(f"/proc/{process.pid}/status")
                .read_text()
                .split("Uid:")[1]
                .split()[0]
            )
        else:
            uid = subprocess.run(
                ["podman", "top", name, "uid"],
                check=True,
                capture_output=True,
                text=True,
            ).stdout.split()[-1]
        assert uid == str(UID), uid
        print("uid:", uid)
    finally:
        if process is not None:
            process.terminate()
            process.wait(timeout=10)
        if args.mode == "podman":
            subprocess.run(
                ["podman", "rm", "-f", name], capture_output=True, check=False
            )
        shutil.rmtree(tmp, ignore_errors=True)
    print(f"container smoke test passed ({args.mode})")


if __name__ == "__main__":
    main()
