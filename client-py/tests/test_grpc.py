"""The gRPC transport (the Rust client of ``esa_client._native``) answers as the engine does.

The parity tests of the in-process engine (``test_inprocess.py``) run again with the gRPC
client of a second real server in place of the engine: the same random scripts through both
clients give identical answers and states, and every bad input raises the same exception type,
status code, failing item and message. Then what only a remote transport has: TCP, the auth
token, a dead server, a deadline, a closed client; and that no gRPC path imports grpcio.
"""

import importlib.util
import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from esa_client import (
    DeadlineExceeded,
    EsaClient,
    ServerUnavailable,
    SessionNotFound,
    StatusCode,
    Unauthenticated,
)
from esa_client._native import GrpcClient
from esa_client.transports.grpc import GrpcTransport


def sibling(name: str) -> ModuleType:
    """Another test module of this folder (``--import-mode=importlib`` keeps it off sys.path)."""
    spec = importlib.util.spec_from_file_location(
        f"_native_grpc_{name}", Path(__file__).with_name(f"{name}.py")
    )
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


_parity = sibling("test_inprocess")
# Collected here too, with this module's ``local``: the gRPC client of another server.
test_unary_scripts_are_identical = _parity.test_unary_scripts_are_identical
test_batch_scripts_are_identical = _parity.test_batch_scripts_are_identical
test_bad_inputs_raise_alike_and_change_nothing = (
    _parity.test_bad_inputs_raise_alike_and_change_nothing
)
CONFIG = _parity.CONFIG
freeze = sibling("test_lifecycle").freeze
TOKEN = "grpc-s3cret-" + "z" * 18


@pytest.fixture(scope="module")
def local(server_bin):
    """A second private server on a Unix socket."""
    with EsaClient.spawn(server_bin) as c:
        yield c


def step_pair(client: EsaClient) -> np.ndarray:
    """A batch's probe and report through ``client``; returns the improved actions."""
    batch = client.create_batch(CONFIG, 2)
    probes = batch.probe(np.zeros((2, 2)), [True, True])
    improved = batch.report(-np.sum(probes**2, axis=1))
    batch.close()
    assert improved is not None
    return improved


def test_the_factories_choose_the_transport(local, client):
    assert isinstance(local.transport, GrpcTransport) and local.healthy()
    assert local.address.startswith("unix:")
    with EsaClient.connect(local.address) as other:
        assert isinstance(other.transport, GrpcTransport)
        assert (step_pair(other) == step_pair(local)).all()
    assert repr(other) == f"EsaClient({local.address!r}, GrpcTransport())"


def test_no_grpc_path_imports_grpcio(local):
    # A None entry makes any `import grpc` fail: the run proves that nothing imports it.
    code = (
        "import sys; sys.modules['grpc'] = None\n"
        "from esa_client import EsaClient, SessionConfig\n"
        f"with EsaClient.connect({local.address!r}) as c:\n"
        "    c.create_session(SessionConfig(1, 0.05, 0.2, 10.0, 0.1)).close()\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)


def test_the_constructor_takes_a_transport_not_an_address(local):
    with pytest.raises(TypeError, match=r"use EsaClient.connect\('127.0.0.1:1'\)"):
        EsaClient("127.0.0.1:1", address="127.0.0.1:1", timeout=1.0)  # type: ignore[arg-type]
    wrapped = EsaClient(GrpcTransport(local.address, 5.0), address="mine", timeout=5.0)
    with wrapped:
        assert wrapped.healthy() and wrapped.servers == () and wrapped.server is None


@pytest.mark.parametrize(
    ("arguments", "match"),
    [
        ({"transport": "pigeon"}, "transport"),
        ({"transport": "native"}, "transport in"),
        ({"shards": 2}, "shards with transport='zenoh' only"),
        ({"prefix": "esa/v1"}, "prefix with transport='zenoh' only"),
        ({"transport": "zenoh", "tls": object()}, "tls=None with transport='zenoh'"),
    ],
)
def test_connect_refuses_arguments_its_transport_does_not_take(arguments, match):
    with pytest.raises(ValueError, match=match):
        EsaClient.connect("127.0.0.1:1", **arguments)


def test_tcp_and_the_auth_token(server_bin, serve_tcp, tmp_path):
    token_file = tmp_path / "token"
    token_file.write_text(TOKEN)
    with serve_tcp(server_bin, "--auth-token-file", str(token_file)) as address:
        with EsaClient.connect(address, token=TOKEN) as owner:
            assert owner.healthy(wait_for_ready=True)
            with EsaClient.in_process() as engine:
                assert (step_pair(owner) == step_pair(engine)).all()
        for token in (None, "wrong"):
            # Refused when connecting: a wrong token fails before any training starts.
            with pytest.raises(Unauthenticated, match=f"at {address} refused this client"):
                EsaClient.connect(address, token=token)
            with EsaClient.connect(address, token=token, check=False) as stranger:
                assert stranger.healthy()  # health needs no token
                with pytest.raises(Unauthenticated) as info:
                    stranger.create_session(CONFIG)
                assert info.value.code == StatusCode.UNAUTHENTICATED


@pytest.mark.parametrize("address", ["127.0.0.1:1", "unix:/nonexistent/esa.sock"])
def test_connect_fails_at_once_where_nothing_listens(address):
    start = time.monotonic()
    with pytest.raises(ServerUnavailable, match=f"no esa server answered at {address} within 2 s"):
        EsaClient.connect(address, timeout=2)
    assert time.monotonic() - start < 10


def test_open_parses_where_the_sessions_live(local):
    with EsaClient.open(local.address) as other:
        assert isinstance(other.transport, GrpcTransport) and other.address == local.address
    with EsaClient.open("in-process") as engine:
        assert engine.address == "in-process"
    for where in ("", "gpu", "sidecar"):
        with pytest.raises(ValueError, match="expected 'in-process', 'spawn'"):
            EsaClient.open(where)
    with pytest.raises(ServerUnavailable, match="127.0.0.1:1"):
        EsaClient.open("127.0.0.1:1")


def test_a_dead_server_is_unavailable(server_bin, monkeypatch):
    monkeypatch.delenv("ESA_AUTH_TOKEN", raising=False)
    with EsaClient.connect("unix:/nonexistent/esa.sock", timeout=2, check=False) as nobody:
        assert not nobody.healthy(timeout=0.2, wait_for_ready=True)
        with pytest.raises(ServerUnavailable) as info:
            nobody.create_session(CONFIG)
        assert info.value.code == StatusCode.UNAVAILABLE
    with EsaClient.spawn(server_bin, reconnect_timeout=0) as client:
        batch = client.create_batch(CONFIG, 2)
        batch.probe(np.zeros((2, 2)), [True, True])
        assert client.server is not None
        client.server.stop()
        with pytest.raises(ServerUnavailable):
            batch.report([1.0, 2.0])


def test_a_frozen_server_hits_the_deadline(server_bin):
    with EsaClient.spawn(server_bin, timeout=0.5) as client:
        session = client.create_session(CONFIG)
        assert client.server is not None
        freeze(client.server.pid)
        try:
            with pytest.raises(DeadlineExceeded) as info:
                session.probe([0.0, 0.0], episode_start=True)
            assert info.value.code == StatusCode.DEADLINE_EXCEEDED
        finally:
            os.kill(client.server.pid, signal.SIGCONT)
        assert session.probe([0.0, 0.0], episode_start=True).shape == (2,)


def test_an_idle_connection_answers_the_servers_pings(server_bin):
    # The server closes a connection whose ping goes unanswered for 2.5 s; no call runs here.
    keepalive = ["--keepalive-interval", "0.3", "--keepalive-timeout", "2.5"]
    with EsaClient.spawn(server_bin, extra_args=keepalive) as client:
        batch = client.create_batch(CONFIG, 2)
        batch.probe(np.zeros((2, 2)), [True, True])
        time.sleep(3.5)
        assert batch.report([1.0, 2.0]).shape == (2, 2)
        assert client.server is not None
        assert "closed" not in client.server.output_tail().lower()


def test_a_closed_client_is_unavailable(server_bin, local):
    with EsaClient.connect(local.address) as other:
        batch = other.create_batch(CONFIG, 1, ids=[f"closed-{uuid.uuid4()}"])
    with pytest.raises(ServerUnavailable, match="closed"):
        batch.probe(np.zeros((1, 2)))
    with pytest.raises(SessionNotFound):
        local.session_state("ghost")


def test_addresses_are_checked():
    for address in ("localhost", "unix:", "host:port"):
        with pytest.raises(ValueError):
            EsaClient.connect(address)
    with pytest.raises(ValueError, match="timeout"):
        GrpcTransport("127.0.0.1:1", float("inf"))
    with pytest.raises(ValueError, match="tls=True"):
        GrpcClient("127.0.0.1:1", 1.0, ca=b"-----BEGIN CERTIFICATE-----")
    with pytest.raises(ValueError, match="both cert and key"):
        GrpcClient("127.0.0.1:1", 1.0, tls=True, cert=b"-----BEGIN CERTIFICATE-----")
