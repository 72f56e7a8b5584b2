"""Hardening from the client's side: typed errors for limits, tokens, unguessable ids,
sidecars that die with their trainer, spawn limits and restoring lost sessions."""

import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import numpy as np
import pytest
import raw_grpc

from esa_client import (
    EsaClient,
    InvalidArgument,
    ResourceExhausted,
    SessionConfig,
    SessionNotFound,
    StatusCode,
    Unauthenticated,
)
from esa_client._proto.esa.v1 import esa_pb2
from esa_client.client import resolve_token
from esa_client.errors import esa_error

CONFIG = SessionConfig(action_dim=2, dt=0.05, amplitude=0.2, frequency=10.0, learning_rate=0.5)
TOKEN = "s3cret-" + "x" * 20


def dead(pid: int) -> bool:
    """True once ``pid`` has exited (a zombie nobody reaped counts as exited)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return True
    return state == "Z"


def wait_until(condition, seconds: float) -> bool:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.05)
    return condition()


def test_batch_ids_are_independent_uuids(client):
    batch = client.create_batch(CONFIG, 8)
    parsed = [uuid.UUID(session_id) for session_id in batch.ids]
    assert all(u.version == 4 and str(u) == i for u, i in zip(parsed, batch.ids, strict=True))
    assert len(set(batch.ids)) == 8
    batch.close()


def test_undecodable_requests_are_invalid_argument(client):
    garbage = raw_grpc.channel(client.server.address).unary_unary("/esa.v1.EsaService/ProbeBatch")
    with pytest.raises(InvalidArgument, match="expected an encoded"):
        raw_grpc.call(garbage, b"\xff\xff\xff", client.timeout)


def test_an_oversize_request_is_resource_exhausted(server_bin):
    with EsaClient.spawn(server_bin, extra_args=["--max-message-bytes", "65536"]) as small:
        batch = small.create_batch(SessionConfig(4096, 0.05, 0.2, 10.0, 0.5), 3)
        with pytest.raises(ResourceExhausted, match="--max-message-bytes"):
            batch.probe(np.zeros((3, 4096)), [True] * 3)
        # Within the limit all is well.
        small.create_batch(CONFIG, 2).probe(np.zeros((2, 2)), [True, True])


def test_a_spawned_servers_session_memory_is_budgeted(server_bin):
    big = SessionConfig(4096, 0.05, 0.2, 10.0, 0.5)
    with EsaClient.spawn(server_bin, max_session_memory=2 << 20) as small:
        created = 0
        with pytest.raises(ResourceExhausted, match="--max-session-memory"):
            while created < 100:
                small.create_session(big)
                created += 1
        assert 3 <= created < 10


@pytest.mark.parametrize(
    "limits",
    [
        dict(max_sessions=0),
        dict(max_sessions=2.5),
        dict(session_ttl=-1),
        dict(max_session_memory="1GiB"),
        dict(max_session_memory=True),
    ],
)
def test_spawn_limits_are_checked(server_bin, limits):
    with pytest.raises(ValueError, match=f"expected {next(iter(limits))}"):
        EsaClient.spawn(server_bin, **limits)


@pytest.fixture(scope="module")
def guarded(server_bin, tmp_path_factory):
    """A server that requires TOKEN; the client spawn returns sends none."""
    token_file = tmp_path_factory.mktemp("token") / "token"
    token_file.write_text(TOKEN + "\n")
    token_file.chmod(0o600)
    with EsaClient.spawn(server_bin, extra_args=["--auth-token-file", str(token_file)]) as c:
        yield c, token_file


def test_without_the_token_calls_are_unauthenticated(guarded):
    stranger, _ = guarded
    assert stranger.healthy()  # health needs no token
    with pytest.raises(Unauthenticated, match="auth token") as info:
        stranger.create_session(CONFIG)
    assert info.value.code == StatusCode.UNAUTHENTICATED
    with pytest.raises(Unauthenticated, match="refused this client"):
        EsaClient.connect(stranger.address, token="wrong")


@pytest.mark.parametrize("use_stream", [False, True], ids=["batch", "stream"])
def test_the_token_can_come_from_an_argument_a_file_or_the_environment(
    guarded, monkeypatch, use_stream
):
    stranger, token_file = guarded
    monkeypatch.setenv("ESA_AUTH_TOKEN", TOKEN)
    for kwargs in (dict(token=TOKEN), dict(token_file=token_file), {}):
        with EsaClient.connect(stranger.address, **kwargs) as owner:
            batch = owner.create_batch(CONFIG, 2, use_stream=use_stream)
            assert batch.probe(np.zeros((2, 2)), [True, True]).shape == (2, 2)
            batch.close()


def test_tokens_are_resolved_strictly(tmp_path, monkeypatch):
    monkeypatch.delenv("ESA_AUTH_TOKEN", raising=False)
    assert resolve_token(None, None) is None
    assert resolve_token(" abc \n", None) == "abc"
    (tmp_path / "t").write_text("from-file\n")
    assert resolve_token(None, tmp_path / "t") == "from-file"
    with pytest.raises(ValueError, match="got both"):
        resolve_token("a", tmp_path / "t")
    with pytest.raises(ValueError, match="non-empty"):
        resolve_token("  ", None)
    monkeypatch.setenv("ESA_AUTH_TOKEN", "")
    with pytest.raises(ValueError, match="ESA_AUTH_TOKEN"):
        resolve_token(None, None)


def test_unauthenticated_maps_from_stream_errors_too():
    error = esa_error(esa_pb2.StreamError(code=16, message="token"))
    assert isinstance(error, Unauthenticated) and isinstance(error, PermissionError)


# The trainer must be able to die of each signal, even when the tests run under nohup
# (which ignores SIGHUP in every child).
TRAINER = """
import signal, sys, time
from esa_client import EsaClient
signal.signal(signal.SIGHUP, signal.SIG_DFL)
client = EsaClient.spawn(sys.argv[1])
print(client.server.pid, client.server.socket_path.parent, flush=True)
time.sleep(60)
"""


@pytest.mark.parametrize("signum", [signal.SIGKILL, signal.SIGTERM, signal.SIGHUP])
def test_the_sidecar_dies_with_its_trainer_and_cleans_up(server_bin, signum):
    trainer = subprocess.Popen(
        [sys.executable, "-c", TRAINER, server_bin], stdout=subprocess.PIPE, text=True
    )
    try:
        pid, workdir = trainer.stdout.readline().split()
        trainer.send_signal(signum)
        trainer.wait(timeout=10)
        assert wait_until(lambda: dead(int(pid)), 5), f"the server outlived {signum.name}"
        assert wait_until(lambda: not Path(workdir).exists(), 5), "its directory was left"
    finally:
        trainer.kill()
        trainer.wait()


def test_lost_sessions_are_restored_at_the_next_episode(server_bin):
    with EsaClient.spawn(server_bin, session_ttl=0.3) as client:
        batch = client.create_batch(CONFIG, 3)
        batch.probe(np.zeros((3, 2)), [True] * 3)
        kept = client.create_session(CONFIG)
        for _ in range(4):  # the batch idles past the TTL; `kept` is used meanwhile
            time.sleep(0.15)
            kept.state()
        with pytest.raises(SessionNotFound):
            client.session_state(batch.ids[0])
        assert client.restore_sessions([*batch.ids, kept.id], CONFIG) == 3
        assert client.sessions_restored == 3
        for session_id in batch.ids:
            state = client.session_state(session_id)
            assert (state.step, state.probe_pending, state.episodes_completed) == (0, False, 0)
        assert client.restore_sessions(batch.ids, batch.configs) == 0


def test_the_sidecar_is_private(client):
    server = client.server
    assert (server.socket_path.stat().st_mode & 0o777) == 0o600
    assert (server.socket_path.parent.stat().st_mode & 0o777) == 0o700
    assert os.stat(server.socket_path).st_uid == os.getuid()
