"""What the end-to-end tests share: a loopback proxy that cuts or swallows connections."""

from __future__ import annotations

import contextlib
import socket
import threading
from collections.abc import Callable, Iterator

import pytest


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
