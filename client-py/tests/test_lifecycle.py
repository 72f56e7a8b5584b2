"""Spawning and stopping the server, and what the client does when the server goes away."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from esa_client import (
    DeadlineExceeded,
    EsaClient,
    EsaError,
    ServerUnavailable,
    SessionConfig,
)

CONFIG = SessionConfig(action_dim=1, dt=0.05, amplitude=0.2, frequency=10.0, learning_rate=0.5)


def gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return False


def freeze(pid: int) -> None:
    """SIGSTOPs the process and waits until the kernel reports every thread stopped."""
    os.kill(pid, signal.SIGSTOP)
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline:
        states = [
            (task / "stat").read_text().rsplit(")", 1)[1].split()[0]
            for task in Path(f"/proc/{pid}/task").iterdir()
        ]
        if all(state == "T" for state in states):
            return
    raise AssertionError(f"process {pid} did not stop")


def test_spawn_and_close_leave_nothing_behind(server_bin):
    with EsaClient.spawn(server_bin) as client:
        server = client.server
        assert client.healthy()
        assert server.socket_path.exists()
        session = client.create_session(CONFIG)
        session.probe([0.0], episode_start=True)
    assert gone(server.pid)
    assert not server.socket_path.parent.exists()
    client.close()  # idempotent


def test_interpreter_exit_stops_an_unclosed_server(server_bin):
    script = (
        "from esa_client import EsaClient; import sys; "
        f"c = EsaClient.spawn({server_bin!r}); "
        "print(c.server.pid, c.server.socket_path.parent, flush=True)"
    )
    result = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=60, check=True
    )
    pid, workdir = result.stdout.split()
    assert gone(int(pid))
    assert not Path(workdir).exists()


def test_missing_or_failing_binaries_give_clear_errors(tmp_path):
    with pytest.raises(EsaError, match="expected an executable esa-server"):
        EsaClient.spawn(tmp_path / "no-such-server")
    failing = tmp_path / "esa-server"
    failing.write_text("#!/bin/sh\necho 'cannot bind: simulated failure' >&2\nexit 3\n")
    failing.chmod(0o755)
    with pytest.raises(ServerUnavailable, match="simulated failure") as info:
        EsaClient.spawn(failing, startup_timeout=10)
    assert "exited with code 3" in str(info.value)


def test_env_var_locates_the_binary(server_bin, monkeypatch):
    monkeypatch.setenv("ESA_SERVER_BIN", server_bin)
    with EsaClient.spawn() as client:
        assert str(client.server.binary) == server_bin


def test_address_validation():
    for bad in ("localhost", "unix:", "host:port", ":50051"):
        with pytest.raises(ValueError, match="expected"):
            EsaClient.connect(bad)


def test_unreachable_server_fails_fast():
    client = EsaClient.connect("unix:/nonexistent/esa.sock", timeout=5.0, check=False)
    start = time.monotonic()
    with pytest.raises(ServerUnavailable):
        client.create_session(CONFIG)
    assert time.monotonic() - start < 2.0
    assert not client.healthy(timeout=0.2)
    client.close()


@pytest.mark.parametrize("path", ["unary", "batch", "stream"])
def test_killed_server_gives_server_unavailable_quickly(server_bin, path):
    # reconnect_timeout=0: a batch raises the first failure (tests/test_chaos.py: retries).
    client = EsaClient.spawn(server_bin, timeout=5.0, reconnect_timeout=0)
    if path == "unary":
        session = client.create_session(CONFIG)
        session.probe([0.0], episode_start=True)
        step = lambda: session.report(1.0)  # noqa: E731
    else:
        batch = client.create_batch(CONFIG, 3, use_stream=path == "stream")
        batch.probe(np.zeros((3, 1)), [True] * 3)
        step = lambda: batch.report([1.0, 2.0, 3.0])  # noqa: E731
    os.kill(client.server.pid, signal.SIGKILL)
    client.server._process.wait()
    start = time.monotonic()
    with pytest.raises(ServerUnavailable):
        step()
    assert time.monotonic() - start < 2.0
    client.close()


@pytest.mark.parametrize("use_stream", [False, True], ids=["batch", "stream"])
def test_frozen_server_hits_the_deadline_then_recovers(server_bin, use_stream):
    with EsaClient.spawn(server_bin, timeout=0.5, reconnect_timeout=0) as client:
        batch = client.create_batch(CONFIG, 2, use_stream=use_stream)
        batch.probe(np.zeros((2, 1)), [True, True])
        freeze(client.server.pid)
        try:
            start = time.monotonic()
            with pytest.raises(DeadlineExceeded):
                batch.report([1.0, 2.0])
            assert time.monotonic() - start < 3.0
        finally:
            os.kill(client.server.pid, signal.SIGCONT)
        # The report may or may not have been applied; repeating it is safe either way.
        improved = batch.report([1.0, 2.0])
        assert improved.shape == (2, 1)
        np.testing.assert_array_equal(batch.steps, [1, 1])
        assert [s.step for s in batch.states()] == [1, 1]
