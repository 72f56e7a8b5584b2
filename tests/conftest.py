"""What the end-to-end tests share: esa-server processes to stop and start again on one
address, and a loopback proxy that cuts or swallows connections."""

from __future__ import annotations

import contextlib
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from esa_client import EsaError
from esa_client.sidecar import find_server_binary

REPO_ROOT = Path(__file__).resolve().parents[1]


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


class ServerProcess:
    """The real esa-server on a fixed loopback port, to signal, kill, stop and start again.

    The port stays the server's across starts, so that a client sees one address go down and
    come back, as behind a Kubernetes Service.

    Args:
        *extra: Further command-line arguments of the server.
        zenoh: Serve Zenoh on the port (gRPC then listens on a port of its own).
        state_file: The ``--state-file``: a stop must leave it written.
    """

    def __init__(
        self, *extra: str, zenoh: bool = False, state_file: Path | None = None
    ) -> None:
        try:
            self.binary = str(find_server_binary(checkout=REPO_ROOT, build=False))
        except EsaError as err:
            pytest.fail(str(err))
        port = _free_port()
        self.zenoh = zenoh
        self.address = f"tcp/127.0.0.1:{port}" if zenoh else f"127.0.0.1:{port}"
        self.state_file = state_file
        state = ["--state-file", str(state_file)] if state_file is not None else []
        listen = ["127.0.0.1:0", "--zenoh", "--zenoh-listen"] if zenoh else []
        self.command = [self.binary, "--listen", *listen, self.address, *state, *extra]
        self.process: subprocess.Popen[str] | None = None
        self.starts = 0
        self.start()

    def start(self) -> None:
        """Starts the server; retries while the port lingers after a kill or stop."""
        deadline = time.monotonic() + 10
        ready = "zenoh listening" if self.zenoh else "listening on "
        while True:
            process = subprocess.Popen(
                self.command,
                stdout=subprocess.PIPE,
                stderr=subprocess.DEVNULL,
                text=True,
            )
            assert process.stdout is not None
            for line in process.stdout:
                if line.startswith(ready):
                    self.process = process
                    self.starts += 1
                    return
            process.wait()
            assert time.monotonic() < deadline, "the server did not start again"
            time.sleep(0.05)

    def signal(self, number: int) -> None:
        assert self.process is not None
        self.process.send_signal(number)

    def kill(self) -> None:
        """SIGKILL: everything in the server's memory is lost."""
        self.signal(signal.SIGKILL)
        assert self.process is not None
        self.process.wait()

    def stop(self) -> None:
        """SIGTERM: the server finishes what is in flight, writes its state file, exits 0."""
        self.signal(signal.SIGTERM)
        assert self.process is not None
        assert self.process.wait(timeout=30) == 0
        assert self.state_file is None or self.state_file.exists()

    def restart(self, down: float = 1.5) -> None:
        """SIGKILL, ``down`` seconds without a server, then a new one on the same address."""
        self.kill()
        time.sleep(down)
        self.start()

    def stop_and_start(self, down: float = 1.0) -> None:
        """SIGTERM, ``down`` seconds without a server, then a new one on the same address."""
        self.stop()
        time.sleep(down)
        self.start()

    def start_later(self, down: float) -> threading.Thread:
        """Starts the server again after ``down`` seconds, on a thread of its own."""
        thread = threading.Thread(
            target=lambda: (time.sleep(down), self.start()), daemon=True
        )
        thread.start()
        return thread

    def close(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.send_signal(signal.SIGCONT)
            self.process.kill()
            self.process.wait()


@pytest.fixture
def esa_server() -> Iterator[Callable[..., ServerProcess]]:
    """Starts esa-servers (``ServerProcess``'s arguments); each is killed when the test ends."""
    servers: list[ServerProcess] = []

    def make(
        *extra: str, zenoh: bool = False, state_file: Path | None = None
    ) -> ServerProcess:
        servers.append(ServerProcess(*extra, zenoh=zenoh, state_file=state_file))
        return servers[-1]

    yield make
    for server in servers:
        server.close()


@pytest.fixture
def free_port() -> Callable[[], int]:
    """A loopback port free now (for a server the test starts itself)."""
    return _free_port


class Proxy:
    """A loopback TCP proxy to ``upstream`` whose connections can all be cut at once.

    While ``holding``, it drops everything it is sent (a request that never reaches the
    server); a cut ends that too.
    """

    def __init__(self, upstream: str) -> None:
        host, port = upstream.rsplit(":", 1)
        self._upstream = (host, int(port))
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.address = f"127.0.0.1:{self._listener.getsockname()[1]}"
        self._sockets: list[socket.socket] = []
        self._lock = threading.Lock()
        self.cuts = 0
        self.holding = False
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self._listener.accept()
            except OSError:
                return
            upstream = socket.create_connection(self._upstream)
            with self._lock:
                self._sockets += [client, upstream]
            for a, b in ((client, upstream), (upstream, client)):
                threading.Thread(target=self._pump, args=(a, b), daemon=True).start()

    def _pump(self, source: socket.socket, sink: socket.socket) -> None:
        with contextlib.suppress(OSError):
            while data := source.recv(65536):
                if not self.holding:
                    sink.sendall(data)
        for sock in (source, sink):
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)

    def cut(self) -> None:
        """Breaks every open connection (the server keeps its sessions); new ones are forwarded."""
        with self._lock:
            sockets, self._sockets = self._sockets, []
            self.cuts += 1
            self.holding = False
        for sock in sockets:
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)
            sock.close()

    def close(self) -> None:
        self._listener.close()
        self.cut()


@pytest.fixture
def loopback_proxy() -> Iterator[Callable[[str], Proxy]]:
    """Makes proxies to an address; each is closed when the test ends."""
    proxies: list[Proxy] = []

    def make(upstream: str) -> Proxy:
        proxies.append(Proxy(upstream))
        return proxies[-1]

    yield make
    for proxy in proxies:
        proxy.close()
