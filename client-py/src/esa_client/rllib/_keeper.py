"""Keeper of a node's shared esa-server (run as a script: it imports nothing but the stdlib).

``python _keeper.py DIR BINARY [SERVER ARGS...]`` forks into the background (the first
process exits at once, so the keeper is nobody's child: Ray kills the children of a
worker that exits), starts ``BINARY --uds DIR/esa-PID.sock --parent-pid PID ...`` as its
child, waits for the server's ``listening on`` line, then writes ``DIR/server.json``
(address and pids) atomically, or ``DIR/server.failed`` if the server does not start:
from then on the server is the node's sidecar. Every runner that uses it holds a shared ``flock`` on
``DIR/users.lock`` for as long as it does (the kernel drops it when the runner exits,
however it exits). The keeper polls that lock: once it can take it exclusively (no
user left) and also ``DIR/start.lock`` (no runner is starting or joining), it removes
``server.json``, stops the server and exits, holding ``start.lock`` until the server
is gone, so that the next runner starts a fresh one on a clean directory. It also
exits, removing ``server.json``, if the server dies. The server follows the keeper if
the keeper is killed (``--parent-pid``).

Runners start the keeper while holding ``start.lock`` exclusively
(:mod:`esa_client.rllib.service`), so two runners never start two servers.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

POLL_SECONDS = 0.5
STARTUP_SECONDS = 60.0
STOP_GRACE_SECONDS = 5.0


def _try_lock(fd: int, kind: int) -> bool:
    try:
        fcntl.flock(fd, kind | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    return True


def _stop(server: subprocess.Popen[bytes]) -> None:
    if server.poll() is None:
        server.send_signal(signal.SIGTERM)
        try:
            server.wait(timeout=STOP_GRACE_SECONDS)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait()


def _forget(info: Path, pid: int) -> None:
    """Removes ``server.json`` if it is this keeper's record (not a successor's)."""
    with contextlib.suppress(OSError, ValueError):
        if json.loads(info.read_text()).get("keeper_pid") == pid:
            info.unlink()


def _wait_listening(server: subprocess.Popen[bytes], log: Path) -> str | None:
    """The address from the server's ``listening on ADDR`` line; None if it exits or hangs."""
    deadline = time.monotonic() + STARTUP_SECONDS
    while time.monotonic() < deadline:
        if server.poll() is not None:
            return None
        with contextlib.suppress(OSError):
            for line in log.read_text(errors="replace").splitlines():
                if line.startswith("listening on "):
                    return line[len("listening on ") :].strip()
        time.sleep(0.01)
    return None


def main(argv: list[str]) -> int:
    """Runs the keeper; returns its exit status."""
    directory, binary, server_args = Path(argv[0]), argv[1], argv[2:]
    # Detach: the runner that starts us waits for this first process only, and our parent
    # becomes init. Ray kills the child processes of a worker that exits; the node's
    # sidecar must outlive the runner that happened to start it.
    if os.fork() > 0:
        os._exit(0)
    pid = os.getpid()
    failed = directory / "server.failed"
    socket = directory / f"esa-{pid}.sock"
    info = directory / "server.json"
    log = directory / "server.log"
    users = os.open(directory / "users.lock", os.O_RDWR | os.O_CREAT, 0o600)
    start = os.open(directory / "start.lock", os.O_RDWR | os.O_CREAT, 0o600)
    command = [binary, "--uds", str(socket), "--parent-pid", str(pid), *server_args]
    with open(log, "wb") as out:
        server = subprocess.Popen(
            command,
            stdin=subprocess.DEVNULL,
            stdout=out,
            stderr=subprocess.STDOUT,
            env={**os.environ, "NO_COLOR": "1"},
        )

    def terminate(*_: object) -> None:
        # SIGTERM (e.g. a cleanup of the node) stops the server too.
        _forget(info, pid)
        _stop(server)
        sys.exit(0)

    signal.signal(signal.SIGTERM, terminate)
    address = _wait_listening(server, log)
    if address is None:
        _stop(server)
        message = f"esa-server did not start: {' '.join(command)}"
        print(message, file=sys.stderr)
        failed.write_text(json.dumps({"keeper_pid": pid, "message": message}))
        return 1
    tmp = directory / f"server.json.{pid}"
    tmp.write_text(json.dumps({"address": address, "keeper_pid": pid, "server_pid": server.pid}))
    os.replace(tmp, info)
    print(f"serving {address} (server pid {server.pid})", file=sys.stderr, flush=True)
    while True:
        time.sleep(POLL_SECONDS)
        if server.poll() is not None:
            print(f"esa-server exited with code {server.returncode}", file=sys.stderr)
            _forget(info, pid)
            return 1
        if not _try_lock(users, fcntl.LOCK_EX):
            continue
        if _try_lock(start, fcntl.LOCK_EX):
            # No user and nobody joining: stop, then let the locks go (at exit).
            _forget(info, pid)
            _stop(server)
            with contextlib.suppress(FileNotFoundError):
                socket.unlink()
            print("no runner left: stopped", file=sys.stderr)
            return 0
        # A runner is joining (it holds start.lock and waits for users.lock): let it.
        fcntl.flock(users, fcntl.LOCK_UN)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
