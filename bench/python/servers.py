"""Starting the servers the Python benchmarks talk to, as child processes on loopback."""

from __future__ import annotations

import signal
import subprocess
import sys
from collections.abc import Iterator, Sequence
from contextlib import AbstractContextManager, contextmanager
from pathlib import Path

from esa_client import EsaError
from esa_client.sidecar import find_server_binary

REPO_ROOT = Path(__file__).resolve().parents[2]


def server_binary() -> str:
    """The esa-server binary, found as the client finds it (``find_server_binary``).

    ``ESA_SERVER_BIN`` (``make bench`` sets it) wins, then the ``esa-server`` wheel,
    then this checkout's release build (never built here).
    """
    try:
        return str(find_server_binary(checkout=REPO_ROOT, build=False))
    except EsaError as err:
        raise SystemExit(str(err)) from err


@contextmanager
def serving(args: Sequence[str]) -> Iterator[str]:
    """Runs a server that prints ``listening on ADDR`` once bound; yields ADDR, then stops it."""
    process = subprocess.Popen(
        list(args), stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
    )
    try:
        line = process.stdout.readline() if process.stdout else ""
        if not line.startswith("listening on "):
            raise RuntimeError(f"{args[0]} did not start: {line!r}")
        yield line.split()[-1]
    finally:
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def esa_server_tcp() -> AbstractContextManager[str]:
    """The real esa-server on 127.0.0.1 with a free port."""
    return serving([server_binary(), "--listen", "127.0.0.1:0", "--session-ttl", "0"])


def echo_server(listen: str) -> AbstractContextManager[str]:
    """The bare grpcio echo (``echo_server.py``) at ``listen`` (``127.0.0.1:0``, ``unix:/path``)."""
    script = Path(__file__).with_name("echo_server.py")
    return serving([sys.executable, str(script), "--listen", listen])
